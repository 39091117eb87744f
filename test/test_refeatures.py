"""The replay pipeline: a live lockstep run recorded by the launcher, its images run again
through detector + features (+ the servo, open loop) offline by ``refeatures`` and, over ROS,
by ``replay`` into the real ``detector`` and ``features`` nodes; both reproduce the recorded
``features/s_n`` message for message."""
from __future__ import annotations

import io
import re
import subprocess
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path

import numpy as np
import pytest

from conftest import _acquire_domain_id, executable_path

pytest.importorskip('rclpy')
from rosbags.highlevel import AnyReader  # noqa: E402
from rosbags.rosbag2 import StoragePlugin, Writer  # noqa: E402

from sphere_servo.tools import bagio, refeatures as rf  # noqa: E402


@pytest.fixture(scope='module')
def lockstep_run(install_space, tmp_path_factory):
    """A live lockstep special-sphere run to convergence, recorded by the launcher:
    (bag path, launcher log, the stamp of the image the launcher last taught)."""
    tmp = tmp_path_factory.mktemp('lockstep')
    domain, lock = _acquire_domain_id()  # held while the run's nodes live
    env = dict(install_space, ROS_DOMAIN_ID=str(domain), PYTHONUNBUFFERED='1',
               ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    env.pop('ROS_LOCALHOST_ONLY', None)
    bag = tmp / 'bag'
    try:
        out = subprocess.run([executable_path(env, 'launcher'), '--config', 'special_sphere',
                              '--until-converged', '--timeout', '90', '--record', str(bag)],
                             env=env, capture_output=True, text=True, timeout=150)
    finally:
        lock.close()
    log = out.stdout + out.stderr
    assert out.returncode == 0, log[-4000:]
    taught = re.findall(r'desired features taught from the image stamped (\d+)\.(\d{9})', log)
    assert taught, log[-4000:]
    sec, ns = taught[-1]
    return bag, log, int(sec) * 1_000_000_000 + int(ns)


def test_regenerated_s_n_equals_recorded(lockstep_run, install_space, tmp_path):
    bag, log, taught = lockstep_run
    res = rf.regenerate(bag, rf.load_settings('special_sphere'), servo=True)
    # the desired is found in the bag: the image the launcher's teach used
    assert res.desired[-1].frame.stamp == taught, [d.note for d in res.desired]
    # the detector reproduces every recorded measurement exactly
    meas = rf.compare_recorded(res, rf.MEAS_TOPIC)
    assert meas.common > 100 and meas.ok(partial=True), meas
    # s_n: message for message, same image stamps, same numbers
    rec = res.recorded['/features/s_n']
    gen = res.streams['/features/s_n']
    assert len(gen) == len(rec) > 100
    assert [rf.stamp_ns(m.header) for _, m in gen] == [rf.stamp_ns(m.header) for _, m in rec]
    for (_, a), (_, b) in zip(rec, gen):
        assert list(a.name) == list(b.name)
        np.testing.assert_allclose(b.position, a.position, rtol=0, atol=1e-12)
        np.testing.assert_allclose(b.velocity, a.velocity, rtol=0, atol=1e-12)
        np.testing.assert_allclose(b.effort, a.effort, rtol=0, atol=1e-12)
    # the open-loop servo: every recorded twist (the servo is stopped before the last
    # images, so some may be missing) is reproduced
    tw = rf.compare_recorded(res, rf.TWIST_TOPIC)
    assert tw.recorded > 100 and tw.matched == tw.recorded and tw.ok(1e-12, partial=True), tw
    assert tw.regenerated - tw.recorded <= 5, tw

    # the installed command: the same verdict, and a new bag with the regenerated streams
    out_bag = tmp_path / 'regen'
    p = subprocess.run([executable_path(install_space, 'refeatures'), str(bag), '--config',
                        'special_sphere', '--servo', '--check', '-o', str(out_bag),
                        '--storage', 'sqlite3'],
                       env=install_space, capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stdout + p.stderr
    assert re.search(r'/features/s_n\s+(\d+)\s+\1\s+same\s+0\b', p.stdout), p.stdout
    with AnyReader([out_bag], default_typestore=bagio.typestore()) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
    assert counts == {rf.MEAS_TOPIC: len(res.frames), '/features/s_n': len(rec),
                      rf.TWIST_TOPIC: tw.regenerated}


def test_compare_sets_plot(lockstep_run, tmp_path):
    bag, _, _ = lockstep_run
    png = tmp_path / 'cmp.png'
    out = io.StringIO()
    with redirect_stdout(out):
        code = rf.main([str(bag), '--config', 'special_sphere', '--compare', 's_n', 's',
                        's_cc', '--plot', str(png)])
    text = out.getvalue()
    assert code == 0, text
    assert png.is_file() and png.stat().st_size > 20_000
    rows = {ln.split()[0]: ln.split() for ln in text.splitlines()
            if ln.split() and ln.split()[0] in ('s_n', 's', 's_cc')}
    assert set(rows) == {'s_n', 's', 's_cc'}
    n = {r[1] for r in rows.values()}
    assert len(n) == 1 and int(n.pop()) > 100  # the same images for every set
    # the s_n run converged in the recording, so its open-loop error ends below tol
    assert float(rows['s_n'][4]) < 5e-4


def test_replay_over_ros_reproduces_s_n(lockstep_run, launch, test_node, tmp_path):
    """(a) over ROS: the taught image exported as a PNG, the bag's images replayed into the
    real detector and features nodes (desired_source: image); their s_n after the teach
    equals the recorded one."""
    from sensor_msgs.msg import JointState
    bag, _, taught = lockstep_run
    png = tmp_path / 'desired.png'
    assert rf.main([str(bag), '--export-desired', str(png)]) == 0
    node, spin = test_node
    got = []
    node.create_subscription(JointState, '/features/s_n', lambda m: got.append(m), 100)
    det = launch('detector')
    feat = launch('features', '--ros-args', '-p', 'desired_source:=image',
                  '-p', f'desired_image:={png}')
    with bagio.bag(bag) as reader:
        rec = rf.read_topic(reader, '/features/s_n')
    spin(20.0, until=lambda: node.count_publishers('/features/s_n') > 0 and
         node.count_subscribers('/detector/measurement') > 0 and
         node.count_publishers('/detector/measurement') > 0)
    rep = launch('replay', str(bag), '--topics', '/camera/image_raw', '/camera/camera_info',
                 '--wait-for-subscribers', '15', '--delay', '0.5')
    last = rf.stamp_ns(rec[-1][1].header)
    spin(60.0, until=lambda: rep.popen.poll() is not None and got and
         rf.stamp_ns(got[-1].header) >= last)
    spin(0.5)
    assert rep.popen.wait(10) == 0, rep.log()
    assert 'error' not in (det.log() + feat.log()).lower(), det.log() + feat.log()
    # after the last teach: the same messages, in the same order
    after = [(st, m) for _, m in rec if (st := rf.stamp_ns(m.header)) > taught]
    live = [(st, m) for m in got if (st := rf.stamp_ns(m.header)) > taught]
    assert len(live) == len(after) > 100
    for (sa, a), (sb, b) in zip(after, live):
        assert sa == sb and list(a.name) == list(b.name)
        np.testing.assert_allclose(b.position, a.position, rtol=0, atol=1e-12)
        np.testing.assert_allclose(b.velocity, a.velocity, rtol=0, atol=1e-12)


# --- bad input: one line, non-zero exit ---------------------------------------------------

def _run(argv) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with redirect_stdout(out), redirect_stderr(err):
        try:
            code = rf.main(argv)
        except SystemExit as exc:  # argparse
            code = exc.code
    return code, out.getvalue(), err.getvalue()


def _images_only_bag(path: Path) -> None:
    ts = bagio.typestore()
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conn = w.add_connection('/camera/camera_info', 'sensor_msgs/msg/CameraInfo',
                                typestore=ts)
        T = ts.types
        msg = T['sensor_msgs/msg/CameraInfo'](
            header=T['std_msgs/msg/Header'](stamp=T['builtin_interfaces/msg/Time'](
                sec=1, nanosec=0), frame_id='c'),
            height=48, width=64, distortion_model='plumb_bob', d=np.zeros(5),
            k=np.array([60.0, 0, 32, 0, 60, 24, 0, 0, 1]), r=np.eye(3).ravel(),
            p=np.zeros(12), binning_x=0, binning_y=0,
            roi=T['sensor_msgs/msg/RegionOfInterest'](x_offset=0, y_offset=0, height=0,
                                                      width=0, do_rectify=False))
        w.write(conn, 1, ts.serialize_cdr(msg, 'sensor_msgs/msg/CameraInfo'))
        conn = w.add_connection('/camera/image_raw', 'sensor_msgs/msg/Image', typestore=ts)
        img = T['sensor_msgs/msg/Image'](
            header=msg.header, height=48, width=64, encoding='rgb8', is_bigendian=0,
            step=192, data=np.zeros(48 * 192, np.uint8))
        w.write(conn, 2, ts.serialize_cdr(img, 'sensor_msgs/msg/Image'))


def test_bad_inputs(tmp_path):
    (tmp_path / 'notabag').mkdir()
    _images_only_bag(tmp_path / 'images')
    cases = {
        'missing path': [str(tmp_path / 'nope')],
        'not a bag': [str(tmp_path / 'notabag')],
        'no desired in the bag': [str(tmp_path / 'images')],
        'no such image stamp': [str(tmp_path / 'images'), '--desired', 'stamp:7.5'],
        'bad desired spec': [str(tmp_path / 'images'), '--desired', 'pose:1,2'],
        'unknown topic': [str(tmp_path / 'images'), '--image-topic', '/no/such'],
        'existing output': [str(tmp_path / 'images'), '--desired', 'stamp:1.0', '-o',
                            str(tmp_path / 'images')],
        'unknown config': [str(tmp_path / 'images'), '--config', 'no_such_config'],
    }
    for what, argv in cases.items():
        code, out, err = _run(argv)
        lines = [ln for ln in err.splitlines() if ln.strip()]
        assert code != 0, f'{what}: exit 0\n{out}{err}'
        assert len(lines) == 1 and 'error:' in lines[0], f'{what}: {err!r}'
        assert 'Traceback' not in out + err
    # a blank image: no sphere, so the taught image cannot anchor the features
    code, _, err = _run([str(tmp_path / 'images'), '--desired', 'stamp:1.0'])
    assert code == 1 and 'cannot teach' in err, err
