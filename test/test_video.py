"""
Test the video of a run (``experiments/video.py``), made from a recorded bag.

The bag is a UR5 servo run recorded from the nodes' cores and codecs (``run_bag``). The
video is decoded with OpenCV and measured on its pixels: the sphere found in the frame
against the goal ring drawn in it, and the goal ring against the taught measurement.
"""
from __future__ import annotations

from contextlib import redirect_stderr, redirect_stdout
import io
from pathlib import Path

import cv2
import numpy as np
import pytest
from run_bag import run_bag
from sphere_servo.bag.run import read_run
from sphere_servo.experiments import video

W, H = 640, 480


@pytest.fixture(scope='module')
def recorded(tmp_path_factory):
    return run_bag(tmp_path_factory.getbasetemp())


@pytest.fixture(scope='module')
def made(recorded, tmp_path_factory):
    """Make the video and GIF of the recorded run with the CLI: (path, stdout, stderr)."""
    out = tmp_path_factory.mktemp('video') / 'v.mp4'
    code, stdout, err = _run([recorded.bag, '-o', out, '--gif'])
    assert code == 0, err
    return out, stdout, err


def _run(argv) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with redirect_stdout(out), redirect_stderr(err):
        try:
            code = video.main([str(a) for a in argv])
        except SystemExit as exc:  # argparse
            code = exc.code
    return code, out.getvalue(), err.getvalue()


def _decode(path: Path) -> list[np.ndarray]:
    cap = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, f = cap.read()
        if not ok:
            break
        frames.append(f[..., ::-1])  # rgb
    cap.release()
    return frames


def sphere_centre(img: np.ndarray) -> np.ndarray:
    """
    Find the centre (u, v) of the sphere in an rgb image.

    The largest bright, colourless blob, its holes (the marks) filled.
    """
    g = img.astype(int)
    body = ((g.min(axis=2) > 110) & (np.ptp(g, axis=2) < 45)).astype(np.uint8)
    n, lab, stats, _ = cv2.connectedComponentsWithStats(body)
    assert n > 1, 'no sphere in the frame'
    k = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    cs, _ = cv2.findContours((lab == k).astype(np.uint8), cv2.RETR_EXTERNAL,
                             cv2.CHAIN_APPROX_NONE)
    filled = np.zeros_like(body)
    cv2.drawContours(filled, cs, -1, 1, -1)
    m = cv2.moments(filled, True)
    assert m['m00'] > 2000, 'the sphere blob is too small'
    return np.array([m['m10'] / m['m00'], m['m01'] / m['m00']])


def goal_ring(img: np.ndarray) -> tuple[np.ndarray, float]:
    """Centre and mean diameter of the magenta ring drawn in an rgb image."""
    g = img.astype(int)
    mask = (g[..., 0] > 150) & (g[..., 2] > 150) & (g[..., 1] < 120)
    pts = np.argwhere(mask)[:, ::-1].astype(np.float32)
    assert len(pts) > 100, f'no goal ring in the frame ({len(pts)} magenta pixels)'
    (cx, cy), (a, b), _ = cv2.fitEllipse(pts)
    return np.array([cx, cy]), (a + b) / 2


def test_video_decodes_with_one_frame_per_servo_iteration(recorded, made, tmp_path):
    out, stdout, err = made
    frames = _decode(out)
    assert len(frames) == recorded.iterations > 100
    assert frames[0].shape == (H, W + H, 3)
    assert 'video: ' in err  # the progress bar
    assert str(out) in stdout and 'desired (taught)' in stdout
    gif = out.with_suffix('.gif')
    cap = cv2.VideoCapture(str(gif))
    n_gif = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
    # 10 fps of a 30 fps video, half size
    assert abs(n_gif - recorded.iterations / 3) <= 2, n_gif
    assert cap.read()[1].shape[:2] == (H // 2, (W + H) // 2)
    # every image of the bag (re-publications once): the teach frames too
    code, _, err = _run([recorded.bag, '-o', tmp_path / 'all.mp4', '--every-image',
                         '--quiet'])
    assert code == 0, err
    assert len(_decode(tmp_path / 'all.mp4')) == recorded.images


def test_target_starts_away_from_the_goal_and_ends_on_it(recorded, made):
    frames = _decode(made[0])
    cams = [f[:H, :W] for f in frames]
    ring0, d0 = goal_ring(cams[0])
    ring1, d1 = goal_ring(cams[-1])
    # the ring is where the taught measurement says, in every frame
    taught = recorded.desired_meas
    for ring, d in ((ring0, d0), (ring1, d1)):
        np.testing.assert_allclose(ring, [taught['ellipse_u'], taught['ellipse_v']], atol=1.5)
        assert abs(d - (taught['ellipse_major'] + taught['ellipse_minor']) / 2) < 3
    first = np.linalg.norm(sphere_centre(cams[0]) - ring0)
    last = np.linalg.norm(sphere_centre(cams[-1]) - ring1)
    assert first > 0.5 * d0, f'first frame: sphere {first:.1f} px from the goal'
    assert last < 2.0, f'last frame: sphere {last:.1f} px from the goal'
    # the plots grow: hardly any curve at the first frame, the whole run at the last
    panel0, panel1 = (f[video.LEGEND_H:, W:].astype(int) for f in (frames[0], frames[-1]))
    coloured0, coloured1 = ((np.ptp(p, axis=2) > 60).sum() for p in (panel0, panel1))
    assert coloured1 > 5 * max(coloured0, 1) and coloured1 > 1000, (coloured0, coloured1)


def test_frames_and_desired_of_the_run(recorded):
    run = read_run(recorded.bag)
    # one frame per iteration, as the servo counted them in its recorded states
    assert len(run.frames) == run.iterations == recorded.iterations
    assert run.desired.how == 'taught' and run.desired.stamp == recorded.taught_stamp
    assert run.desired.values == recorded.desired_meas
    assert run.frames == sorted(run.frames)
    np.testing.assert_allclose(run.series(run.joints, 6), np.array(recorded.frames_q),
                               atol=1e-12)


def test_desired_without_features_is_the_last_converged_image(tmp_path):
    rec = run_bag(tmp_path, 'nofeatures', with_features=False, gain=2.0)
    run = read_run(rec.bag)
    assert run.desired.how == 'last converged'
    assert run.desired.stamp == run.frames[-1]
    assert 'no features/<set>/desired messages' in run.desired.note


def _bag(path: Path, with_image_topic: bool) -> None:
    from rosbags.rosbag2 import StoragePlugin, Writer
    from sensor_msgs.msg import JointState

    from sphere_servo.bag.bagio import typestore
    from sphere_servo.bag.compare import cdr
    from sphere_servo.ros.conversions import header
    ts = typestore()
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conn = w.add_connection('/joint_states', 'sensor_msgs/msg/JointState', typestore=ts)
        msg = JointState(header=header(1.0, ''), name=['a'], position=[0.0])
        w.write(conn, 1, cdr(msg, 'sensor_msgs/msg/JointState'))
        if with_image_topic:
            w.add_connection('/camera/image_raw', 'sensor_msgs/msg/Image', typestore=ts)


def test_a_bag_without_images_fails_with_a_message(tmp_path):
    _bag(tmp_path / 'joints', with_image_topic=False)
    _bag(tmp_path / 'empty_topic', with_image_topic=True)
    (tmp_path / 'notabag').mkdir()
    cases = {'joints': 'no images: topic /camera/image_raw is not in the bag',
             'empty_topic': 'no images: topic /camera/image_raw has no message',
             'notabag': 'not a rosbag2 bag', 'nope': 'does not exist'}
    for name, text in cases.items():
        out = tmp_path / f'{name}.mp4'
        code, stdout, err = _run([tmp_path / name, '-o', out])
        lines = [ln for ln in err.splitlines() if ln.strip()]
        assert code == 1, f'{name}: exit {code}'
        assert len(lines) == 1 and lines[0].startswith('video: error:') and text in lines[0], \
            f'{name}: {err!r}'
        assert not out.exists() and 'Traceback' not in stdout + err
    code, _, err = _run([tmp_path / 'joints', '--fps', '0'])
    assert code == 1 and '--fps' in err


def test_the_demo_writes_the_video_the_gif_and_the_page(recorded, tmp_path):
    """``make demo``'s last step, on the recorded run: all three files, from its bag."""
    from sphere_servo.experiments.demo import watch_files
    files = watch_files(recorded.bag, tmp_path, 'special_sphere')
    assert files == [tmp_path / 'servo.mp4', tmp_path / 'servo.gif', tmp_path / 'replay.html']
    assert len(_decode(files[0])) == recorded.iterations
    assert cv2.VideoCapture(str(files[1])).read()[0]
    assert '<title>replay: ' in files[2].read_text(encoding='utf-8')
