"""
``video``: a video of a run, made from its recorded rosbag2.

    python -m sphere_servo.experiments.video BAG [-o OUT.mp4] [--gif [GIF]] [--config NAME]
                                             [--every-image] [--fps F]
                                             [--image-topic T]
    make video BAG=runs/<timestamp>/bag

A camera bag recorded with image_transport's compressed topic: ``--image-topic
/camera/image_raw/compressed`` (JPEG or PNG; each frame shown in the colour order its
format names).

One frame per servo iteration (the frames of :func:`sphere_servo.bag.run.read_run`: every
image the servo answered while enabled, by its recorded ``servo/state``; ``--every-image``:
every image of the bag), at the camera's rate (``--fps`` to change it). Each frame: on the
left the camera image with

- the detection: the recorded ``detector/measurement``'s ellipse (green) and marks (yellow
  crosses) — so any bag with images and measurements works, whatever made it;
- the goal: the desired measurement's ellipse (magenta) and marks (circles in the marks'
  colours) — the recorded measurement of the image the run taught (the header of its
  recorded ``features/<set>/desired``), else the last converged image's, else none (the
  frame says so);

and on the right the servo's error norm ‖s − s*‖₂ (its ``servo/state``; log scale), the
twist's translation (m/s) and rotation (deg/s) in the camera frame, up to that frame.

Writes H.264 (``yuv420p``, CRF 20) with the ffmpeg that ``imageio-ffmpeg`` ships, to
``OUT`` (default: ``servo.mp4`` beside the bag directory, i.e. ``runs/<ts>/servo.mp4``);
``--gif`` also writes a small GIF (10 fps, half size, 128 colours; default ``servo.gif``
beside OUT). Exit code 0 when the video was written, 1 (one line on stderr, and no video
left behind) when it was not: the bag cannot be read, has no images, images that are not
``sensor_msgs/msg/Image`` or ``CompressedImage``, not 8-bit, that cannot be decoded (a bad
buffer, corrupt or truncated JPEG/PNG bytes, compressedDepth: the image is named), or not
stamped (stamp 0: they cannot be told apart), measurements of a mark the ``--config``
target has not, a frame rate out of :data:`FPS_RANGE`, or the output cannot be written. The
overlays are drawn in each image's own pixels (the measurements'), whatever ``camera_info``
says; the frame has the first image's size. When the servo counted more iterations than the
bag has states for (the recorder lost some), the tool says how many are not in the video.
"""
from __future__ import annotations

import argparse
from dataclasses import dataclass
import itertools
from pathlib import Path
import subprocess
import sys
import time

import cv2
import numpy as np

from sphere_servo.bag.bagio import BagError
from sphere_servo.bag.offline import IMAGE_TOPIC, load_settings
from sphere_servo.bag.run import (cli_error, iter_frames, output_path, print_warnings,
                                  read_run, Run)
from sphere_servo.core.targets import make_target

GREEN, MAGENTA, YELLOW, WHITE = (0, 230, 0), (255, 0, 255), (255, 230, 0), (255, 255, 255)
#: pixels (or degrees) beyond which a recorded value is not drawn (OpenCV refuses it)
DRAW_LIMIT = 1e6
LEGEND_H = 26  # px above the plots, for the overlay's legend
CRF = 20
#: the frame rates written (ffmpeg rounds a rate to a fraction of denominator <= 10^6)
FPS_RANGE = (0.01, 1000.0)


class ProgressBar:
    """A text progress bar on stderr (redrawn in place on a terminal, else every 25 %)."""

    def __init__(self, total: int, label: str, stream=None, width: int = 30):
        self.total, self.label, self.width = max(int(total), 1), label, width
        self.stream = sys.stderr if stream is None else stream
        self.tty = hasattr(self.stream, 'isatty') and self.stream.isatty()
        self._last, self._quarter = 0.0, -1

    def update(self, done: int) -> None:
        """Show ``done`` of ``total`` (throttled to 10 redraws a second on a terminal)."""
        frac = min(max(done / self.total, 0.0), 1.0)
        if self.tty:
            now = time.monotonic()
            if now - self._last < 0.1 and done < self.total:
                return
            self._last = now
            bar = '#' * int(round(frac * self.width))
            self.stream.write(f'\r{self.label} [{bar:<{self.width}}] {done}/{self.total}')
            if done >= self.total:
                self.stream.write('\n')
        elif int(frac * 4) > self._quarter:
            self._quarter = int(frac * 4)
            self.stream.write(f'{self.label}: {done}/{self.total}\n')
        self.stream.flush()


def _drawable(*values) -> bool:
    """Tell whether numbers can be drawn: finite, within :data:`DRAW_LIMIT` of 0."""
    return all(np.isfinite(x) and abs(x) <= DRAW_LIMIT for x in values)


def draw_measurement(img: np.ndarray, values: dict, ring, marks: dict, cross: bool,
                     thickness: int = 1) -> None:
    """
    Draw a ``detector/measurement`` (as name → value) on an rgb8 image, in place.

    The ellipse (``ellipse_u ellipse_v ellipse_major ellipse_minor ellipse_angle``, pixels
    and degrees) in colour ``ring``; each mark ``M_u M_v`` as a cross (``cross``) or a
    circle, in the colour ``marks[M]``. What cannot be drawn (not finite, beyond
    :data:`DRAW_LIMIT`, a negative axis) is left out.
    """
    if not values:
        return
    try:
        box = ((values['ellipse_u'], values['ellipse_v']),
               (values['ellipse_major'], values['ellipse_minor']), values['ellipse_angle'])
    except KeyError:
        box = None
    if box is not None and _drawable(*box[0], *box[1], box[2]) and min(box[1]) >= 0:
        cv2.ellipse(img, box, ring, thickness, cv2.LINE_AA)
    for name, color in marks.items():
        u, v = values.get(f'{name}_u'), values.get(f'{name}_v')
        if u is None or v is None or not _drawable(u, v):
            continue
        c = (int(round(u)), int(round(v)))
        if cross:
            cv2.drawMarker(img, c, color, cv2.MARKER_CROSS, 12, thickness, cv2.LINE_AA)
        else:
            cv2.circle(img, c, 8, color, thickness + 1, cv2.LINE_AA)


def _text(img, lines, org, scale: float = 0.5) -> None:
    """
    Draw lines of ``(text, colour)`` on a translucent dark box at ``org`` (top left).

    The box keeps the text readable on any image.
    """
    lines = [ln for ln in lines if ln[0]]
    if not lines:
        return
    font, step = cv2.FONT_HERSHEY_SIMPLEX, int(22 * scale / 0.5)
    w = max(cv2.getTextSize(t, font, scale, 1)[0][0] for t, _ in lines)
    x0, y0 = org
    x1, y1 = min(x0 + w + 12, img.shape[1]), min(y0 + step * len(lines) + 6, img.shape[0])
    roi = img[y0:y1, x0:x1]
    roi[:] = (roi * 0.45).astype(np.uint8)
    for i, (t, color) in enumerate(lines):
        cv2.putText(img, t, (x0 + 6, y0 + step * (i + 1) - 4), font, scale, color, 1,
                    cv2.LINE_AA)


class PlotPanel:
    """
    The right-hand panel: ‖s − s*‖ (log), v (m/s) and ω (deg/s) against time.

    The axes, ticks and labels are drawn once with matplotlib over the whole run; each
    frame copies that background and draws the curves up to the frame with OpenCV (a frame
    costs well under a millisecond this way).
    """

    def __init__(self, t: np.ndarray, err: np.ndarray, twist: np.ndarray, width: int,
                 height: int, label: str):
        import matplotlib
        matplotlib.use('Agg')
        import matplotlib.pyplot as plt
        self.t = t
        v, w = twist[:, :3], np.degrees(twist[:, 3:])
        fig, axes = plt.subplots(3, 1, figsize=(width / 100, height / 100), dpi=100,
                                 sharex=True)
        span = (0.0, max(float(t[-1]), 1e-3))
        finite = err[np.isfinite(err) & (err > 0)]
        lo, hi = (finite.min(), finite.max()) if finite.size else (1e-4, 1.0)
        axes[0].set_yscale('log')
        axes[0].set_ylim(lo / 2, hi * 2)
        axes[0].set_ylabel(f'‖s − s*‖ ({label})', fontsize=8)
        for ax, data, name in ((axes[1], v, 'v (m/s)'), (axes[2], w, 'ω (deg/s)')):
            good = data[np.isfinite(data)]
            m = max(float(np.max(np.abs(good))) if good.size else 0.0, 1e-6) * 1.1
            ax.set_ylim(-m, m)
            ax.set_ylabel(name, fontsize=8)
            ax.axhline(0.0, color='0.6', lw=0.5)
        axes[-1].set_xlabel('t (s)', fontsize=8)
        for ax in axes:
            ax.set_xlim(*span)
            ax.grid(alpha=0.3)
            ax.tick_params(labelsize=7)
        colors = [tuple(int(255 * c) for c in matplotlib.colors.to_rgb(f'C{i}'))
                  for i in range(3)]
        for ax, names in ((axes[1], ('v_x', 'v_y', 'v_z')), (axes[2], ('ω_x', 'ω_y', 'ω_z'))):
            for name, col in zip(names, colors):
                ax.plot([], [], color=np.array(col) / 255, label=name)
            ax.legend(fontsize=6, ncol=3, loc='upper right')
        fig.tight_layout(pad=0.4)
        fig.canvas.draw()
        self.background = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
        H = self.background.shape[0]

        def to_px(ax, y):
            xy = ax.transData.transform(np.column_stack([t, y]))
            return np.column_stack([xy[:, 0], H - xy[:, 1]])
        self.curves = [(to_px(axes[0], np.where(err > 0, err, np.nan)), (31, 119, 180))]
        for ax, data in ((axes[1], v), (axes[2], w)):
            self.curves += [(to_px(ax, data[:, i]), colors[i]) for i in range(3)]
        self.cursor = [(ax.transData.transform([[0.0, ax.get_ylim()[0]]])[0][1],
                        ax.transData.transform([[0.0, ax.get_ylim()[1]]])[0][1]) for ax in axes]
        self.x_px = axes[0].transData.transform(np.column_stack([t, np.ones_like(t)]))[:, 0]
        plt.close(fig)

    def render(self, k: int) -> np.ndarray:
        """Draw the panel with the curves up to frame ``k`` and a cursor at its time."""
        out = self.background.copy()
        H = out.shape[0]
        for pts, color in self.curves:
            seg = pts[:k + 1]
            ok = np.all(np.isfinite(seg), axis=1)
            # split at NaN (no value for that frame): draw each run of values
            for run in np.split(np.arange(len(seg)), np.flatnonzero(~ok)):
                run = run[ok[run]]
                if len(run) >= 2:
                    cv2.polylines(out, [np.round(seg[run] * 16).astype(np.int32)], False,
                                  color, 1, cv2.LINE_AA, shift=4)
        x = int(round(self.x_px[k]))
        for y0, y1 in self.cursor:
            cv2.line(out, (x, int(H - y0)), (x, int(H - y1)), (150, 150, 150), 1)
        return out


@dataclass
class VideoResult:
    """What :func:`make_video` wrote."""

    path: Path
    frames: int
    fps: float
    size: tuple
    seconds: float
    desired: str
    gif: Path | None = None
    unrecorded: int = 0


class FrameDrawer:
    """
    Compose the video frames of a run (camera image with overlays | plot panel).

    The overlays are drawn on each image at its own size (the measurements are in its
    pixels), then the image is scaled to the frame's: ``size`` (W, H) of the run's first
    image, else the ``camera_info``'s, else 640 × 480. BagError when the recorded
    measurements see a mark the target of ``target_kind`` does not have (another scenario).
    """

    def __init__(self, run: Run, target_kind: str = 'special', size: tuple | None = None):
        if size is not None:
            W, H = (int(x) for x in size)
        elif run.camera is not None:
            W, H = run.camera.width, run.camera.height
        else:
            W, H = 640, 480
        self.run, self.W, self.H = run, W, H
        target = make_target(target_kind)
        colors, names = target.colors, target.mark_names
        self.mark_colors = {n: colors.get(n, colors['P2']) for n in names}
        seen = {k[:-2] for m in run.meas.values() for k in m
                if k.endswith('_u') and k != 'ellipse_u'}
        if seen - set(names):
            raise BagError(f'{run.path}: the measurements see marks '
                           f'{", ".join(sorted(seen - set(names)))} that a {target_kind} '
                           f'target has not ({", ".join(names)}): give --config the run was '
                           'recorded with')
        n = len(run.frames)
        self.err = run.series(run.error_norm, 1)[:, 0]
        self.twist = run.series(run.twists, 6)
        self.t = np.array([run.t(st) for st in run.frames])
        pw = H // 2 * 2
        self.panel = PlotPanel(self.t, self.err, self.twist, pw, H - LEGEND_H,
                               run.feature_set)
        self.size = ((W + pw + 1) // 2 * 2, (H + 1) // 2 * 2)
        self.iterations = n
        d = run.desired
        self.goal = 'no desired measurement in the bag' if d is None else \
            f'desired ({d.how})'
        # the legend sits beside the image, so the image shows only the overlays
        self.legend = np.full((LEGEND_H, pw, 3), 255, np.uint8)
        x = 8
        for text, color in (('detected', GREEN), (self.goal, MAGENTA)):
            cv2.line(self.legend, (x, 13), (x + 18, 13), color, 2, cv2.LINE_AA)
            cv2.putText(self.legend, text, (x + 24, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.45,
                        (0, 0, 0), 1, cv2.LINE_AA)
            x += 24 + cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.45, 1)[0][0] + 16

    def draw(self, k: int, stamp: int, img: np.ndarray) -> np.ndarray:
        """Compose the video frame ``k`` (rgb8, :attr:`size`) of the image stamped ``stamp``."""
        cam = img.copy()
        if self.run.desired is not None:
            draw_measurement(cam, self.run.desired.values, MAGENTA, self.mark_colors,
                             cross=False, thickness=2)
        draw_measurement(cam, self.run.meas.get(stamp, {}), GREEN,
                         {n: YELLOW for n in self.mark_colors}, cross=True)
        if cam.shape[:2] != (self.H, self.W):  # the overlays are in the image's pixels
            cam = cv2.resize(cam, (self.W, self.H), interpolation=cv2.INTER_AREA)
        err = self.err[k]
        state = self.run.states.get(stamp, '')
        lost = stamp in self.run.meas and not self.run.meas[stamp]
        _text(cam, [(f't = {self.t[k]:5.2f} s   iteration {k + 1}/{self.iterations}', WHITE),
                    ((f'|s - s*| = {err:.2e}' if np.isfinite(err) else '|s - s*| = -')
                     + (f'   {state}' if state else ''), WHITE),
                    ('target not detected' if lost else '', (255, 90, 90))], (4, 4))
        out = np.full((self.size[1], self.size[0], 3), 255, np.uint8)
        out[:self.H, :self.W] = cam
        out[:LEGEND_H, self.W:self.W + self.legend.shape[1]] = self.legend
        panel = self.panel.render(k)
        out[LEGEND_H:LEGEND_H + panel.shape[0], self.W:self.W + panel.shape[1]] = panel
        return out


def check_stamps(run: Run) -> None:
    """
    Refuse (BagError) a run with images stamped 0 or before (unset, as ROS tools read it).

    The frames are told apart by their stamps: unstamped images would all be one frame.
    """
    if run.frames[0] <= 0:
        raise BagError(f'{run.path}: images on {run.image_topic} are stamped '
                       f'{run.frames[0] * 1e-9:g} s (unset): the frames of the run cannot be '
                       'told apart')


def make_video(run: Run, out: Path, fps: float | None = None, gif: Path | None = None,
               target_kind: str = 'special', progress: bool = True) -> VideoResult:
    """Write the H.264 video (and the GIF if ``gif``) of ``run``; see the module docstring."""
    import imageio_ffmpeg
    t0 = time.monotonic()
    fps = check_fps(fps, 'fps') if fps else \
        check_fps(run.frame_rate(), "the frames' rate", ': give --fps')
    out = prepare_output(out)
    if gif is not None:
        gif = prepare_output(gif)
    frames = iter_frames(run)
    first = next(frames, None)  # the frame's size, and a bag whose images fail, refused
    if first is None:           # before anything is written
        raise BagError(f'{run.path}: none of the images of the run could be read back')
    drawer = FrameDrawer(run, target_kind, size=first[2].shape[1::-1])
    writer = imageio_ffmpeg.write_frames(
        str(out), drawer.size, fps=fps, codec='libx264', pix_fmt_in='rgb24',
        pix_fmt_out='yuv420p', quality=None, macro_block_size=1,
        output_params=['-crf', str(CRF), '-preset', 'veryfast'])
    writer.send(None)
    bar = ProgressBar(len(run.frames), 'video') if progress else None
    n = 0
    try:
        for k, stamp, img in itertools.chain([first], frames):
            writer.send(np.ascontiguousarray(drawer.draw(k, stamp, img)))
            n += 1
            if bar:
                bar.update(n)
        writer.close()
        if n != len(run.frames):
            raise BagError(f'{run.path}: {len(run.frames) - n} of the images of the run '
                           'could not be read back')
    except BaseException:
        writer.close()
        out.unlink(missing_ok=True)  # no video rather than a part of one
        raise
    res = VideoResult(out, n, fps, drawer.size, 0.0, drawer.goal,
                      unrecorded=unrecorded_iterations(run))
    if gif is not None:
        res.gif = make_gif(out, Path(gif))
    res.seconds = time.monotonic() - t0
    return res


def check_fps(fps: float, what: str, hint: str = '') -> float:
    """Return ``fps`` if it is a frame rate ffmpeg writes (:data:`FPS_RANGE`), else BagError."""
    lo, hi = FPS_RANGE
    if not (np.isfinite(fps) and lo <= fps <= hi):
        raise BagError(f'{what} must be a number of frames a second in [{lo:g}, {hi:g}], got '
                       f'{fps:g}{hint}')
    return float(fps)


def unrecorded_iterations(run: Run) -> int:
    """
    Count the servo's iterations (its last recorded ``iteration``) that are not frames.

    The images whose ``servo/state`` the recorder lost (or a recording started late).
    """
    return max(0, (run.iterations or 0) - len(run.frames))


def prepare_output(path) -> Path:
    """
    Return the output file ``path``, its directory made; OSError saying why it cannot be.

    Refused: an existing directory, a path under a file.
    """
    path = Path(path)
    if path.is_dir():
        raise OSError(f'output {path} is a directory, not a file')
    parent = next((p for p in path.parents if p.exists()), None)
    if parent is not None and not parent.is_dir():
        raise OSError(f'output {path}: {parent} is a file, not a directory')
    path.parent.mkdir(parents=True, exist_ok=True)
    return path


def make_gif(video: Path, gif: Path, fps: float = 10.0, scale: float = 0.5,
             colors: int = 128) -> Path:
    """Write a small GIF of a video (ffmpeg's palettegen/paletteuse, subsampled to ``fps``)."""
    import imageio_ffmpeg
    graph = (f'fps={fps:g},scale=trunc(iw*{scale:g}/2)*2:-2:flags=lanczos,split[a][b];'
             f'[a]palettegen=max_colors={colors}[p];[b][p]paletteuse=dither=bayer')
    cmd = [imageio_ffmpeg.get_ffmpeg_exe(), '-y', '-loglevel', 'error', '-i', str(video),
           '-vf', graph, '-loop', '0', str(gif)]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise OSError(f'ffmpeg could not write {gif}: {proc.stderr.strip()[-300:]}')
    return gif


def parse_args(argv):
    ap = argparse.ArgumentParser(prog='video', description=__doc__.strip().splitlines()[0])
    ap.add_argument('bag', help='rosbag2 directory of the run (runs/<timestamp>/bag)')
    ap.add_argument('-o', '--output', help='video file (default: servo.mp4 beside the bag)')
    ap.add_argument('--gif', nargs='?', const='', default=None,
                    help='also write a GIF (default: servo.gif beside the video)')
    ap.add_argument('--config', default='special_sphere',
                    help='scenario (or params file) the run used: target kind, feature set')
    ap.add_argument('--every-image', action='store_true',
                    help='one frame per image of the bag, not per servo iteration')
    ap.add_argument('--fps', type=float, default=None, help='frame rate (default: camera)')
    ap.add_argument('--image-topic', default=IMAGE_TOPIC,
                    help='sensor_msgs/Image or CompressedImage topic (default: %(default)s)')
    ap.add_argument('--quiet', action='store_true', help='no progress bar')
    return ap.parse_args(argv)


def main(argv=None) -> int:
    opts = parse_args(list(sys.argv[1:] if argv is None else argv))
    from sphere_servo.pipeline.config import ConfigError
    try:
        if opts.fps is not None:
            check_fps(opts.fps, '--fps')
        settings = load_settings(opts.config)
        run = read_run(opts.bag, settings, opts.image_topic, opts.every_image)
        print_warnings('video', run)
        check_stamps(run)
        out = output_path(opts.bag, opts.output, 'servo.mp4')
        gif = None if opts.gif is None else (Path(opts.gif) if opts.gif
                                             else out.with_suffix('.gif'))
        res = make_video(run, out, opts.fps, gif, settings.features.target_kind,
                         progress=not opts.quiet)
    except (BagError, ConfigError, ValueError, OSError) as err:
        return cli_error('video', err)
    print(f'video: {res.frames} frames ({res.size[0]}x{res.size[1]}, {res.fps:g} fps), '
          f'{res.desired}, in {res.seconds:.1f} s'
          + (f'; the servo counted {res.unrecorded} more iterations, whose servo/state the '
             'bag does not have (not in the video)' if res.unrecorded else ''))
    print(f'  {res.path} ({res.path.stat().st_size / 1e6:.2f} MB)')
    if res.gif is not None:
        print(f'  {res.gif} ({res.gif.stat().st_size / 1e6:.2f} MB)')
    return 0


if __name__ == '__main__':
    sys.exit(main())
