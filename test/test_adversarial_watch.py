"""
Adversarial tests of the "watch it" tools: the video and the 3-D replay page of a bag.

The bags are variants of a UR5 run recorded from the nodes' cores (``run_bag``), rewritten
by the ``rosbags`` writer as rosbag2 writes them (:mod:`watch_bags`: sqlite3 or MCAP,
``metadata.yaml``, recorded QoS): joint states reordered, short, long, NaN or past the
joint limits, images re-timed, re-encoded or of another size than ``camera_info``, a run
that never converged, one message, none, a killed recording, a scenario that is not the
bag's, outputs that cannot be written. Each must give a page or video whose content is
right (the page's keys are the valid joint states and its link poses Pinocchio's own
placements of the URDF's visual geometry; the video has one frame per servo iteration and
its goal ring sits on the sphere), or a refusal: exit 1, one line on stderr, no file.
"""
from __future__ import annotations

import os
from pathlib import Path
import shutil

from browser import load
import cv2
import numpy as np
import pinocchio as pin
import pytest
from run_bag import run_bag
from sphere_servo.bag.run import load_arm_params, read_run
from sphere_servo.experiments import replay3d, video
from sphere_servo.sim.arm import pose_from_xyz_rpy
from test_markers import Geometry
from test_replay3d import _commands
from test_video import _decode, goal_ring, sphere_centre
from watch_bags import (chain, doubled, doubled_measurement, on, refused, rewrite, run_tool,
                        scenario, stamp, to_bgr8, to_mono16, to_mono8)

W, H = 640, 480
JOINTS = '/joint_states'


@pytest.fixture(scope='module')
def recorded(tmp_path_factory):
    return run_bag(tmp_path_factory.getbasetemp())


@pytest.fixture(scope='module')
def geometry():
    return Geometry()


@pytest.fixture(scope='module')
def base_video(recorded, tmp_path_factory):
    out = tmp_path_factory.mktemp('watch') / 'base.mp4'
    code, _, err = run_tool(video, [recorded.bag, '-o', out, '--quiet'])
    assert code == 0, err
    return _decode(out)


def page_keys(page: Path) -> dict:
    """Return each animated path's keys: {path: {time: SE3}} (position and quaternion)."""
    cmds = _commands(page.read_text(encoding='utf-8'))
    (anim,) = [c for c in cmds if c['type'] == 'set_animation']
    out = {}
    for a in anim['animations']:
        tracks = {t['name']: t['keys'] for t in a['clip']['tracks']}
        if '.position' not in tracks:
            continue
        out[a['path']] = {
            p['time']: pin.XYZQUATToSE3(np.array(p['value'] + q['value'], dtype=float))
            for p, q in zip(tracks['.position'], tracks['.quaternion'])}
    return out


def check_page(page: Path, run, valid: dict, geometry) -> None:
    """
    Check the page keys exactly the frames of ``valid`` (stamp → q) at their frame numbers.

    Each link's pose at a key is Pinocchio's placement of its visual for that q (to 1e-6:
    float32 in the page), the camera's is the arm's ``wMc`` of the recorded ground truth.
    """
    keys = page_keys(page)
    index = {st: k for k, st in enumerate(run.frames)}
    want = sorted(index[st] for st in valid if st in index)
    assert want, 'no valid frame to check'
    by_k = {index[st]: q for st, q in valid.items() if st in index}
    for i in range(7):
        got = keys[f'/meshcat/robot/{i}']
        assert sorted(got) == want
    assert sorted(keys['/meshcat/camera/0']) == want
    tp = load_arm_params('special_sphere').target_pose
    wMo = pose_from_xyz_rpy(tp[:3], tp[3:])
    st_of = {k: st for st, k in index.items()}
    worst = 0.0
    for k in want[::max(1, len(want) // 25)] + [want[-1]]:
        for i, M in enumerate(geometry.placements(by_k[k])):
            worst = max(worst, float(np.max(np.abs(
                keys[f'/meshcat/robot/{i}'][k].homogeneous - M.homogeneous))))
        if st_of[k] in run.oMc:  # the camera where the recorded ground truth has it
            worst = max(worst, float(np.max(np.abs(
                keys['/meshcat/camera/0'][k].homogeneous
                - (wMo * run.oMc[st_of[k]]).homogeneous))))
    assert worst < 1e-5, worst


def _page(bag: Path, out: Path, *extra) -> str:
    code, stdout, err = run_tool(replay3d, [bag, '-o', out, *extra])
    assert code == 0, err
    assert out.is_file() and str(out) in stdout
    return stdout


@pytest.mark.parametrize('storage', ['sqlite3', 'mcap'])
def test_bags_as_rosbag2_writes_them(recorded, geometry, base_video, tmp_path, storage):
    """sqlite3 and MCAP bags with rosbag2's metadata and QoS: the same page and video."""
    b = rewrite(recorded.bag, tmp_path / 'bag', storage=storage)
    run = read_run(b)
    assert len(run.frames) == recorded.iterations
    _page(b, tmp_path / 'r.html')
    check_page(tmp_path / 'r.html', run, dict(zip(run.frames, recorded.frames_q)), geometry)
    code, _, err = run_tool(video, [b, '-o', tmp_path / 'v.mp4', '--quiet'])
    assert code == 0, err
    frames = _decode(tmp_path / 'v.mp4')
    assert len(frames) == recorded.iterations
    assert np.abs(frames[-1].astype(int) - base_video[-1]).mean() < 1.0


def _reversed(m):
    m.name, m.position = m.name[::-1], np.array(m.position[::-1])
    return m


@pytest.mark.parametrize('what, fn, text', [
    ('reordered', _reversed, 'joint_states name'),
    ('a joint missing', lambda m: setattr(m, 'name', m.name[:-1]) or setattr(
        m, 'position', np.array(m.position[:-1])) or m, 'wrist_3_joint'),
    ('an extra joint', lambda m: setattr(m, 'name', m.name + ['gripper']) or setattr(
        m, 'position', np.append(m.position, 0.3)) or m, 'gripper'),
    ('past the limits', lambda m: setattr(m, 'position', m.position + [0, 0, 4.0, 0, 0, 0])
     or m, 'none of its'),
    ('no joint_states', lambda m: None, 'no joint_states in the bag')])
def test_joint_states_the_model_cannot_take_are_refused(recorded, tmp_path, what, fn, text):
    """Every joint state of a kind the UR5 model cannot show: the page is refused."""
    b = rewrite(recorded.bag, tmp_path / 'bag', on(JOINTS, fn), 'sqlite3')
    refused(replay3d, [b], tmp_path / 'r.html', text)
    # the video does not need joint states: it is made, one frame per servo iteration
    code, _, err = run_tool(video, [b, '-o', tmp_path / 'v.mp4', '--quiet'])
    assert code == 0, err
    assert len(_decode(tmp_path / 'v.mp4')) == recorded.iterations


def test_invalid_joint_states_are_left_out(recorded, geometry, tmp_path):
    """
    A NaN, a short and a past-limit joint state among the run's: the page keys the others.

    Before, one NaN refused the whole page with a message naming no bag.
    """
    run0 = read_run(recorded.bag)
    bad = {run0.frames[40]: 'nan', run0.frames[100]: 'short', run0.frames[200]: 'limit'}

    def spoil(m):
        how = bad.get(stamp(m))
        if how == 'nan':
            m.position = np.array([0.0, np.nan, 0.0, 0.0, 0.0, 0.0]) + m.position
        elif how == 'short':
            m.position = np.array(m.position[:5])
        elif how == 'limit':
            m.position = m.position + [0.0, 0.0, 4.0, 0.0, 0.0, 0.0]  # elbow > π
        return m
    b = rewrite(recorded.bag, tmp_path / 'bag', on(JOINTS, spoil))
    stdout = _page(b, tmp_path / 'r.html')
    assert '3 invalid joint states' in stdout and '3 frames have no recorded joint' in stdout
    assert '3 invalid joint states left out' in (tmp_path / 'r.html').read_text()
    run = read_run(b)
    valid = {st: q for st, q in zip(run0.frames, recorded.frames_q) if st not in bad}
    check_page(tmp_path / 'r.html', run, valid, geometry)
    # and it runs in a real browser, without a JavaScript exception
    seen = load((tmp_path / 'r.html').as_uri())
    assert seen.loaded and seen.exceptions == [], seen.exceptions[:2]


def test_joint_states_are_read_by_name(recorded, geometry, tmp_path):
    """
    Every other joint_states names its joints in reverse order (the last in the model's).

    A JointState is a named vector: the page must show each message's positions on the
    joints it names (or refuse the bag). No ground truth in the bag, so nothing else can
    tell the page it is wrong.
    """
    run0 = read_run(recorded.bag)
    flips = set(run0.frames[:-1:2])
    b = rewrite(recorded.bag, tmp_path / 'bag', chain(
        on(JOINTS, lambda m: _reversed(m) if stamp(m) in flips else m),
        on('/ground_truth/camera_pose', lambda m: None)))
    code, _, err = run_tool(replay3d, [b, '-o', tmp_path / 'r.html'])
    assert code in (0, 1), err
    if code == 0:
        check_page(tmp_path / 'r.html', read_run(b),
                   dict(zip(run0.frames, recorded.frames_q)), geometry)


def test_out_of_order_and_duplicate_stamps(recorded, geometry, base_video, tmp_path):
    """
    Images recorded in reverse bag order; every joint state and servo state twice.

    The frames are in stamp order whatever the bag order: the same video as the run's, and
    a page keyed at every frame with the right poses.
    """
    def reverse(topic, t, m):
        return [(20_000_000_000 - t, m)] if topic == '/camera/image_raw' else [(t, m)]

    def twice(topic, t, m):
        return [(t, m), (t + 1, m)] if topic in (JOINTS, '/servo/state') else [(t, m)]
    b = rewrite(recorded.bag, tmp_path / 'bag', chain(reverse, twice))
    code, _, err = run_tool(video, [b, '-o', tmp_path / 'v.mp4', '--quiet'])
    assert code == 0, err
    frames = _decode(tmp_path / 'v.mp4')
    assert len(frames) == len(base_video) == recorded.iterations
    for k in (0, len(frames) // 2, len(frames) - 1):
        assert np.abs(frames[k].astype(int) - base_video[k]).mean() < 1.0, k
    _page(b, tmp_path / 'r.html')
    run = read_run(b)
    check_page(tmp_path / 'r.html', run, dict(zip(run.frames, recorded.frames_q)), geometry)


@pytest.mark.parametrize('encoding, fn', [('bgr8', to_bgr8), ('mono8', to_mono8)])
def test_images_in_other_encodings(recorded, base_video, tmp_path, encoding, fn):
    """bgr8 and mono8 images: the same frames (mono8: their grey) with the same overlays."""
    b = rewrite(recorded.bag, tmp_path / 'bag', on('/camera/image_raw', fn))
    code, _, err = run_tool(video, [b, '-o', tmp_path / 'v.mp4', '--quiet'])
    assert code == 0, err
    frames = _decode(tmp_path / 'v.mp4')
    assert len(frames) == recorded.iterations
    got, want = frames[0][:H, :W], base_video[0][:H, :W]
    if encoding == 'mono8':  # the grey of the image, the overlays in colour
        got, want = (cv2.cvtColor(np.ascontiguousarray(f), cv2.COLOR_RGB2GRAY)
                     for f in (got, want))
    assert np.abs(got.astype(int) - want).mean() < 2.0
    ring, _ = goal_ring(frames[-1][:H, :W])
    assert np.linalg.norm(sphere_centre(frames[-1][:H, :W]) - ring) < 2.0


def test_an_image_encoding_the_video_cannot_show(recorded, tmp_path):
    """mono16 images: refused, and no broken video left behind (it was, 261 bytes)."""
    b = rewrite(recorded.bag, tmp_path / 'bag', on('/camera/image_raw', to_mono16))
    refused(video, [b, '--quiet'], tmp_path / 'v.mp4', 'mono16')


@pytest.mark.parametrize('case', ['images twice camera_info', 'camera_info twice the images',
                                  'images twice, no camera_info'])
def test_images_of_another_size_than_camera_info(recorded, tmp_path, case):
    """
    Images whose size is not camera_info's: the overlays stay on the sphere.

    The measurements are in the image's pixels. Before, the image was scaled to
    camera_info's size (or 640 × 480) and the overlays drawn on it where the measurement
    says, off the sphere by the scale.
    """
    info = '/camera/camera_info'
    edits = {'images twice camera_info': chain(on('/camera/image_raw', doubled),
                                               on('/detector/measurement',
                                                  doubled_measurement)),
             'camera_info twice the images': on(info, lambda m: setattr(
                 m, 'width', 2 * m.width) or setattr(m, 'height', 2 * m.height) or m),
             'images twice, no camera_info': chain(
                 on('/camera/image_raw', doubled), on(info, lambda m: None),
                 on('/detector/measurement', doubled_measurement))}
    scale = 1 if case.startswith('camera_info') else 2
    b = rewrite(recorded.bag, tmp_path / 'bag', edits[case])
    code, stdout, err = run_tool(video, [b, '-o', tmp_path / 'v.mp4', '--quiet'])
    assert code == 0, err
    frames = _decode(tmp_path / 'v.mp4')
    assert len(frames) == recorded.iterations
    cam = frames[-1][:H * scale, :W * scale]
    ring, d = goal_ring(cam)
    assert np.linalg.norm(sphere_centre(cam) - ring) < 2.0 * scale
    taught = recorded.desired_meas
    assert abs(d - scale * (taught['ellipse_major'] + taught['ellipse_minor']) / 2) < 3 * scale


def _until(n_frames: int, run0):
    """Return an edit keeping only the messages of the first ``n_frames`` servo frames."""
    last = run0.frames[n_frames - 1]

    def edit(topic, t, m):
        if hasattr(m, 'header') and stamp(m) > last:
            return []
        if topic == '/arm_sim/markers':
            return []
        return [(t, m)]
    return edit


def test_a_run_that_never_converged(recorded, geometry, tmp_path):
    """The run cut at its 100th servo iteration: 100 frames, the goal the taught image."""
    run0 = read_run(recorded.bag)
    b = rewrite(recorded.bag, tmp_path / 'bag', _until(100, run0), 'sqlite3')
    code, stdout, err = run_tool(video, [b, '-o', tmp_path / 'v.mp4', '--quiet'])
    assert code == 0, err
    assert len(_decode(tmp_path / 'v.mp4')) == 100 and 'desired (taught)' in stdout
    _page(b, tmp_path / 'r.html')
    check_page(tmp_path / 'r.html', read_run(b),
               dict(zip(run0.frames[:100], recorded.frames_q)), geometry)
    # and without its features: no goal, and the video says so
    b2 = rewrite(b, tmp_path / 'bag2', lambda topic, t, m: [] if topic.startswith(
        '/features/') else [(t, m)])
    code, stdout, err = run_tool(video, [b2, '-o', tmp_path / 'v2.mp4', '--quiet'])
    assert code == 0 and 'no desired measurement in the bag' in stdout, err
    frame = _decode(tmp_path / 'v2.mp4')[-1][:H, :W].astype(int)
    magenta = (frame[..., 0] > 150) & (frame[..., 2] > 150) & (frame[..., 1] < 120)
    assert magenta.sum() < 20  # no goal ring drawn


def test_one_message_and_empty_bags(recorded, tmp_path):
    """One image (nothing else): a one-frame video, the page refused; no message: refused."""
    first = {'done': False}

    def one(topic, t, m):
        if topic != '/camera/image_raw' or first['done']:
            return []
        first['done'] = True
        return [(t, m)]
    b = rewrite(recorded.bag, tmp_path / 'one', one, 'sqlite3')
    code, stdout, err = run_tool(video, [b, '-o', tmp_path / 'v.mp4', '--quiet'])
    assert code == 0, err
    assert len(_decode(tmp_path / 'v.mp4')) == 1
    refused(replay3d, [b], tmp_path / 'r.html', 'no joint_states')
    empty = rewrite(recorded.bag, tmp_path / 'empty', lambda *a: [], 'sqlite3')
    refused(video, [empty], tmp_path / 'e.mp4', 'has no message')
    refused(replay3d, [empty], tmp_path / 'e.html', 'has no message')


@pytest.mark.parametrize('storage, text', [('mcap', 'reindex'), ('sqlite3', 'malformed')])
def test_a_killed_recording(recorded, tmp_path, storage, text):
    """The storage file cut short (its last message truncated): refused, nothing written."""
    b = rewrite(recorded.bag, tmp_path / 'bag', storage=storage)
    (f,) = [p for p in b.iterdir() if p.suffix in ('.mcap', '.db3')]
    data = f.read_bytes()
    f.write_bytes(data[:len(data) - 70_000])
    refused(video, [b, '--quiet'], tmp_path / 'v.mp4', text)
    refused(replay3d, [b], tmp_path / 'r.html', text)


def test_a_scenario_that_is_not_the_bags(recorded, tmp_path):
    """
    ``--config`` of another camera or target: refused (before, the page drew it).

    Another camera (fisheye, catadioptric: the bag's camera_info), another target (the CC
    target's P3 where the bag's measurements see P2). A scenario that differs only in what
    the page does not draw (the servo's r̂) is accepted. Limit: a target of another size is
    not seen (the measured r_delta depends on the detector's intrinsics, off on purpose in
    ``calibration_error``): the page draws the scenario's sphere.
    """
    for cfg, text in (('fisheye', 'camera_info'), ('catadioptric', 'camera_info'),
                      ('cc_target', 'marks P2')):
        refused(replay3d, [recorded.bag, '--config', cfg], tmp_path / 'r.html', text)
    refused(video, [recorded.bag, '--config', 'cc_target', '--quiet'], tmp_path / 'v.mp4',
            'marks P2')
    cfg = scenario(tmp_path, 'bigger_sphere', 'target:\n      radius: 0.06')
    _page(recorded.bag, tmp_path / 'bigger.html', '--config', cfg)
    # a calibration_error run's measurements see the sphere smaller (3.8 cm for 5 cm): its
    # own scenario draws it

    def smaller(m):
        m.position = np.array(m.position)
        if 'r_delta' in m.name:
            m.position[m.name.index('r_delta')] *= 0.76
        return m
    b = rewrite(recorded.bag, tmp_path / 'calib', on('/detector/measurement', smaller))
    _page(b, tmp_path / 'calib.html', '--config', 'calibration_error')
    _page(recorded.bag, tmp_path / 'ok.html', '--config', 'wrong_radius')


def test_outputs_that_cannot_be_written(recorded, tmp_path):
    """A directory, a path under a file, under /proc: refused; a new directory is made."""
    (tmp_path / 'afile').write_text('x')
    (tmp_path / 'adir').mkdir()
    for mod, name in ((video, 'v.mp4'), (replay3d, 'r.html')):
        extra = ['--quiet'] if mod is video else []
        code, _, err = run_tool(mod, [recorded.bag, *extra, '-o', tmp_path / 'adir'])
        assert code == 1 and 'is a directory' in err and len(err.splitlines()) == 1, err
        assert list((tmp_path / 'adir').iterdir()) == []
        refused(mod, [recorded.bag, *extra], tmp_path / 'afile' / name, 'is a file')
        refused(mod, [recorded.bag, *extra], Path('/proc/self/nope') / name, 'error')
        out = tmp_path / 'new' / 'deeper' / name
        code, stdout, err = run_tool(mod, [recorded.bag, *extra, '-o', out])
        assert code == 0 and out.stat().st_size > 1000, err
    assert len(_decode(tmp_path / 'new' / 'deeper' / 'v.mp4')) == recorded.iterations


def test_a_failure_half_way_leaves_no_video(recorded, tmp_path):
    """An image that cannot be decoded after good ones: refused, the partial video removed."""
    run0 = read_run(recorded.bag)
    broken = run0.frames[150]

    def spoil(m):
        if stamp(m) == broken:
            m.encoding = '32FC1'
            m.step = m.width * 4
            m.data = np.zeros(m.height * m.step, np.uint8)
        return m
    b = rewrite(recorded.bag, tmp_path / 'bag', on('/camera/image_raw', spoil))
    refused(video, [b, '--quiet'], tmp_path / 'v.mp4', '32FC1')
    gif = tmp_path / 'v.gif'
    refused(video, [b, '--quiet', '--gif', gif], tmp_path / 'v.mp4', '32FC1')
    assert not gif.exists()
    assert not [p for p in os.listdir(tmp_path) if p.endswith(('.mp4', '.gif'))]
    shutil.rmtree(b)


def test_servo_states_the_recorder_lost(recorded, tmp_path):
    """
    10 of the servo's states lost: their images are not frames, and both tools say so.

    The frames are the images whose recorded state says the servo answered them; the
    servo's own count (its last ``iteration``) tells how many the bag does not show.
    """
    k = {'n': 0}

    def lose(m):
        k['n'] += 1
        return None if 100 <= k['n'] < 110 else m
    b = rewrite(recorded.bag, tmp_path / 'bag', on('/servo/state', lose))
    note = 'the servo counted 10 more iterations'
    code, stdout, err = run_tool(video, [b, '-o', tmp_path / 'v.mp4', '--quiet'])
    assert code == 0 and note in stdout, err
    assert len(_decode(tmp_path / 'v.mp4')) == recorded.iterations - 10
    assert note in _page(b, tmp_path / 'r.html')
