"""
Vision benchmark: detector and renderer speed (prints; never asserted by tests).

- detector median ms/frame on ray-cast frames of the special sphere at 0.25–1.0 m, beside a
  bare ``cvtColor + threshold(Otsu) + findContours + fitEllipse`` on the same frames, at
  640×480 (f = 600 px; target: ratio ≤ 3, median < 3 ms) and 1280×720 (f = 900 px), and
  at 640×480 on a two-level checkerboard (40/70) with a white distractor sphere (the
  candidate search's hard case);
- the detector *cold*: each frame after a 33 ms pause (a 30 Hz camera: between frames the
  caches, the branch predictors and OpenCV's thread pool go cold), beside the same frames
  back to back (warm) as the baseline, on the 640×480 and the checkerboard frames; and
  cold again with the frame's pixels read, or another frame detected, right before it
  (information: which of data and code path the pause leaves cold);
- renderer frames/s for a target filling a quarter of the image (target ≥ 150).

``python -m benchmarks.bench_vision [--quick]`` prints a table.
"""
from __future__ import annotations

import argparse
import time

import cv2
import numpy as np
import pinocchio as pin

from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.targets import cc_target, special_sphere
from sphere_servo.vision.backgrounds import Distractor
from sphere_servo.vision.detector import Detector
from sphere_servo.vision.poses import random_poses
from sphere_servo.vision.renderer import Renderer


HD = CameraIntrinsics(px=900.0, py=900.0, u0=640.0, v0=360.0, width=1280, height=720)


def _frames(n: int, seed: int = 0, cam: CameraIntrinsics | None = None, **kw):
    """
    Render frames of the special sphere at the detector tests' random poses.

    0.25–1.0 m, the sphere fully in view, any orientation; ``kw``: the renderer's
    (background, distractors).
    """
    cam = cam or CameraIntrinsics()
    target = special_sphere()
    ren = Renderer(cam, target, **kw)
    poses = random_poses(target, cam, n, seed, max_incidence=None)
    return cam, target, [ren.render(M) for M in poses]


def baseline_ellipse(img: np.ndarray):
    """Run the bare OpenCV pipeline the detector is compared with."""
    grey = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
    _, mask = cv2.threshold(grey, 0, 255, cv2.THRESH_BINARY | cv2.THRESH_OTSU)
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if not contours:
        return None
    c = max(contours, key=len)
    return cv2.fitEllipse(c) if len(c) >= 5 else None


def _median_ms_pair(fa, fb, frames, repeat: int) -> tuple[float, float]:
    """Median ms of ``fa`` and of ``fb`` per frame, called alternately on each frame."""
    ta, tb = [], []
    for _ in range(repeat):
        for f in frames:
            t0 = time.perf_counter()
            fa(f)
            t1 = time.perf_counter()
            fb(f)
            tb.append(time.perf_counter() - t1)
            ta.append(t1 - t0)
    return 1e3 * float(np.median(ta)), 1e3 * float(np.median(tb))


def _cold_ms(f, frames, repeat: int, gap: float = 0.033, before=None) -> float:
    """
    Median ms of ``f`` per frame, each call after a pause of ``gap`` s (sleeping).

    ``before(frame)``, if given, runs after the pause and before the timed call.
    """
    ts = []
    for _ in range(repeat):
        for fr in frames:
            time.sleep(gap)
            if before is not None:
                before(fr)
            t0 = time.perf_counter()
            f(fr)
            ts.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(ts))


def _row(name, value, unit, target, baseline=None, baseline_name=None):
    ratio = None if baseline in (None, 0) else value / baseline
    return {'name': name, 'value': float(value), 'unit': unit,
            'baseline': None if baseline is None else float(baseline),
            'baseline_name': baseline_name, 'ratio': ratio, 'target': target}


def run(quick: bool = False) -> list[dict]:
    """Measure; returns rows ``{name, value, unit, baseline, baseline_name, ratio, target}``."""
    n, repeat = (15, 2) if quick else (60, 3)
    rows = []
    hard = {'background': 'checker', 'levels': (40, 70), 'seed': 1,
            'distractors': [Distractor('sphere', (-0.1, 0.07, 0.6), 0.05, (250, 250, 250))]}
    for name, cam, kw, target in (
            ('detector median per 640x480 frame', None, {}, 'median < 3 ms and ratio <= 3'),
            ('detector median per 1280x720 frame', HD, {}, 'reported (ratio <= 3)'),
            ('detector 640x480, checker 40/70 + distractor', None, hard, 'reported')):
        cam, tgt, frames = _frames(n, cam=cam, **kw)
        det = Detector.for_target(tgt)
        for f in frames[:3]:                  # warm-up
            det.detect(f, 'rgb8', cam)
            baseline_ellipse(f)
        # interleaved, frame by frame, so that the load of the machine hits both alike
        base, mine = _median_ms_pair(baseline_ellipse, lambda f: det.detect(f, 'rgb8', cam),
                                     frames, repeat)
        rows.append(_row(name, mine, 'ms', target, base,
                         'cv2 threshold+findContours+fitEllipse'))
        if cam is not HD:
            warm = _median_ms_pair(lambda f: det.detect(f, 'rgb8', cam), lambda f: None,
                                   frames, repeat)[0]
            cold = _cold_ms(lambda f: det.detect(f, 'rgb8', cam), frames, repeat)
            rows.append(_row(name.replace('detector', 'detector cold (33 ms apart)', 1), cold,
                             'ms', 'ratio <= 1.5', warm, 'the same, back to back'))
            # what goes cold: the frame's pixels (read once just before) or the code path
            # (another frame detected just before)
            for what, before in (('its image read just before', lambda f: int(f.sum())),
                                 ('another frame detected just before',
                                  lambda f, o=frames[0]: det.detect(o, 'rgb8', cam))):
                ms = _cold_ms(lambda f: det.detect(f, 'rgb8', cam), frames, repeat,
                              before=before)
                rows.append(_row(name.replace('detector', f'detector cold, {what},', 1), ms,
                                 'ms', 'information', cold, 'cold'))
    # a target filling a quarter of the image: disc area W·H/4
    R_px = np.sqrt(cam.width * cam.height / (4 * np.pi))
    for name, tgt in (('special', special_sphere()), ('cc', cc_target())):
        d = cam.px * tgt.radius / R_px
        ren = Renderer(cam, tgt)
        rng = np.random.default_rng(1)
        poses = [pin.SE3(pin.exp3(rng.normal(size=3) * 0.5), np.array([0.0, 0.0, d]))
                 for _ in range(10)]
        ren.render(poses[0])
        k = 3 if quick else 10
        t0 = time.perf_counter()
        for _ in range(k):
            for M in poses:
                ren.render(M)
        fps = k * len(poses) / (time.perf_counter() - t0)
        rows.append(_row(f'renderer {name}, quarter-image target', fps, 'frames/s',
                         '>= 150 frames/s'))
    return rows


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.strip().split('\n\n')[0])
    ap.add_argument('--quick', action='store_true')
    args = ap.parse_args(argv)
    rows = run(args.quick)
    print(f'{"benchmark":45s} {"value":>10s} {"unit":9s} {"baseline":>9s} {"ratio":>6s}  target')
    for r in rows:
        b = '' if r['baseline'] is None else f'{r["baseline"]:.3f}'
        q = '' if r['ratio'] is None else f'{r["ratio"]:.2f}'
        print(f'{r["name"]:45s} {r["value"]:10.3f} {r["unit"]:9s} {b:>9s} {q:>6s}  '
              f'{r["target"]}')


if __name__ == '__main__':
    main()
