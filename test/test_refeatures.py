"""
The replay pipeline: a live lockstep run, its images run again offline and over ROS.

The run is recorded by the launcher; its images go through detector + features (+ the
servo, open loop) offline by ``refeatures`` and, over ROS, by ``replay`` into the real
``detector`` and ``features`` nodes; both reproduce the recorded ``features/s_n`` message
for message.
"""
from __future__ import annotations

from contextlib import redirect_stderr, redirect_stdout
import io
import json
from pathlib import Path
import re
import subprocess
import time

from conftest import _acquire_domain_id, executable_path
import numpy as np
import pytest

pytest.importorskip('rclpy')
from rosbags.highlevel import AnyReader  # noqa: E402
from rosbags.rosbag2 import StoragePlugin, Writer  # noqa: E402
from sphere_servo.bag import bagio, desired, offline, refeatures as rf  # noqa: E402


@pytest.fixture(scope='module')
def lockstep_run(install_space, tmp_path_factory):
    """
    Run the special sphere live in lockstep to convergence, recorded by the launcher.

    Returns (bag path, launcher log, the stamp of the image the launcher last taught).
    """
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


def _features(bag: Path) -> list:
    """(image stamp ns, names, s, s*, s − s*) of every features/s_n message of a bag."""
    with AnyReader([bag], default_typestore=bagio.typestore()) as reader:
        conns = [c for c in reader.connections if c.topic == '/features/s_n']
        return [(offline.header_ns(m.header), list(m.name), m.position, m.velocity, m.effort)
                for m in (reader.deserialize(raw, c.msgtype)
                          for c, _, raw in reader.messages(connections=conns))]


def _stamps(bag: Path, topic: str) -> list:
    """Header stamps (ns) of every message on ``topic``."""
    with AnyReader([bag], default_typestore=bagio.typestore()) as reader:
        conns = [c for c in reader.connections if c.topic == topic]
        return [offline.header_ns(reader.deserialize(raw, c.msgtype).header)
                for c, _, raw in reader.messages(connections=conns)]


def test_regenerated_s_n_equals_recorded(lockstep_run, install_space, tmp_path):
    """
    Regenerate offline the run's features/s_n from its images, message for message.

    With the installed ``refeatures``: the code the live nodes ran.
    """
    bag, log, taught = lockstep_run
    out_bag, report = tmp_path / 'regen', tmp_path / 'report.json'
    p = subprocess.run([executable_path(install_space, 'refeatures'), str(bag), '--config',
                        'special_sphere', '--servo', '--check', '--json', str(report),
                        '-o', str(out_bag), '--storage', 'sqlite3'],
                       env=install_space, capture_output=True, text=True, timeout=120)
    rep = json.loads(report.read_text())
    # the recorder loses nothing (arm_sim keeps 30 images of reliable history, so a recorder
    # starved of CPU for a second still gets them all) and --check passes
    lost = rep['topics']['/features/s_n']['no_image']
    assert lost == 0, f'the recorder lost {lost} images\n{p.stdout}'
    assert p.returncode == 0, p.stdout + p.stderr

    # the desired is found in the bag: the image the launcher last taught
    assert rep['desired'][-1]['taught_stamp_ns'] == taught, rep['desired']
    topics = rep['topics']
    # the detector reproduces every recorded measurement whose image is in the bag
    meas = topics[offline.MEAS_TOPIC]
    assert meas['matched'] == meas['common'] > 100 and meas['max_diff'] == 0.0, meas
    # the open-loop servo answers exactly the images the live servo answered (its recorded
    # states say which: it skips superseded ones, and it is stopped before the last images)
    # and reproduces every recorded twist
    tw = topics[offline.TWIST_TOPIC]
    assert tw['matched'] == tw['recorded'] - tw['no_image'] == tw['regenerated'] > 100, tw
    assert tw['max_diff'] <= 1e-12, tw
    # (the twists that answer an image: the watchdog's carry a zero stamp)
    rec_tw = [t for t in _stamps(bag, offline.TWIST_TOPIC) if t]
    gen_tw = _stamps(out_bag, offline.TWIST_TOPIC)
    assert sorted(gen_tw) == sorted(rec_tw), tw

    # s_n, read back from the two bags: same count, same image stamps, same numbers
    rec, gen = _features(bag), _features(out_bag)
    assert len(gen) == len(rec) > 100 and topics['/features/s_n']['regenerated'] == len(gen)
    for a, b in zip(rec, gen):
        assert a[0] == b[0] and a[1] == b[1]
        for x, y in zip(a[2:], b[2:]):
            np.testing.assert_allclose(y, x, rtol=0, atol=1e-12)
    with AnyReader([out_bag], default_typestore=bagio.typestore()) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
    assert counts == {offline.MEAS_TOPIC: rep['images'], '/features/s_n': len(rec),
                      offline.TWIST_TOPIC: tw['regenerated'],
                      '/features/s_n/desired': len(rep['desired'])}
    # each desired the run taught, regenerated with the taught image's header
    des = topics['/features/s_n/desired']
    assert des['matched'] == des['recorded'] == des['regenerated'] == len(rep['desired'])
    assert des['max_diff'] <= 1e-12, des


def test_launcher_waits_for_the_recorder_before_the_run(lockstep_run):
    """
    Begin the teach sequence only once the recorder records every topic (``--record``).

    So the bag holds the run from its first taught image (under load the recorder used to
    discover the servo's topics after the first teach).
    """
    _, log, _ = lockstep_run
    ready = log.index('[launcher] recording every topic')
    assert ready < log.index('[launcher] arm at the desired pose'), log[:4000]


def test_taught_image_first_in_the_bag(lockstep_run):
    """
    Find the desired in a bag that starts at the taught image.

    Recording began at the teach, or the bag was cut there: the desired is that first
    image, not a crash on an empty search.
    """
    bag, _, taught = lockstep_run
    pipe = offline.Pipeline(offline.load_settings('special_sphere'))
    with bagio.bag(bag) as reader:
        rec = offline.read_topic(reader, offline.features_topic('s_n'))
        des = offline.read_topic(reader, offline.desired_topic('s_n'))
        cams = offline.Cameras(pipe, offline.read_topic(reader, offline.INFO_TOPIC))
        frames = []
        for i, ts, img in offline.iter_image_msgs(reader, offline.IMAGE_TOPIC):
            frames.append(pipe.frame(i, ts, img, cams(ts, offline.header_ns(img.header))))
    # cut the bag at the first features message under the taught s*: its image is frame 0
    rec = [(t, m) for t, m in rec if offline.header_ns(m.header) >= taught]
    des = [(t, m) for t, m in des if offline.header_ns(m.header) == taught]
    first = offline.header_ns(rec[0][1].header)
    k = next(i for i, f in enumerate(frames) if f.stamp == first)
    ds = desired.auto_desired(pipe, frames[k:], {'s_n': rec}, {'s_n': des})
    # the taught image (stamped `taught`) is cut off unless the first features came from a
    # re-publication of it: then it is the image that reproduces its s*
    assert ('is not in the bag' in ds[0].note) == (first > taught), ds[0].note
    # the first desired is taught from the first image itself (an empty search, a crash,
    # before); the lockstep sim may publish that image more than once: as many of its copies
    # get features as the bag has features messages stamped with it
    copies = [f.index for f in frames[k:] if f.stamp == first]
    n = sum(1 for _, m in rec if offline.header_ns(m.header) == first)
    assert ds[0].frame.stamp == first
    assert ds[0].start == copies[-min(n, len(copies))], (copies, n, ds[0].start)


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
    """
    Reproduce the recorded s_n over ROS.

    The taught image exported as a PNG, the bag's images replayed (the installed ``replay``)
    into the real detector and features nodes (desired_source: image); their s_n after the
    teach equals the recorded one, message for message.

    One image is in flight at a time, as in the lockstep run: ``replay --answer
    /camera/image_raw:=/features/s_n`` plays each image once the previous one has its s_n.
    Played at the recorded pace (the lockstep loop's, about 70 Hz), the images outran a
    detector starved of CPU, and its image reader, which keeps the newest 5 by design
    (``qos.SENSOR``), dropped older ones (with four busy loops beside it, 1 to 108 of 275
    in 4 runs of 5; most likely the 282 s_n against 284 of one ``make test`` run).
    """
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import CameraInfo, Image, JointState
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
        rec = offline.read_topic(reader, '/features/s_n')
        stamps = [offline.header_ns(m.header)
                  for _, m in offline.read_topic(reader, '/camera/image_raw')]
    images = set(stamps)
    # prime the chain with the bag's first image until an s_n comes back: then test node ←
    # features ← detector are matched (the graph alone says nothing about matching, and a
    # slow discovery would cost the first replayed images)
    with bagio.bag(bag) as reader:
        first = {}
        for c, _, raw in bagio.iter_raw(reader, [c for c in reader.connections if c.topic in
                                                 ('/camera/image_raw', '/camera/camera_info')]):
            first.setdefault(c.topic, raw)
            if len(first) == 2:
                break
    prime = {t: (node.create_publisher(T, t, 10), deserialize_message(first[t], T))
             for t, T in (('/camera/camera_info', CameraInfo), ('/camera/image_raw', Image))}
    deadline = time.monotonic() + 30.0
    while not got and time.monotonic() < deadline:
        for pub, msg in prime.values():
            pub.publish(msg)
        spin(0.3, until=lambda: bool(got))
    assert got, det.log() + feat.log()
    for pub, _ in prime.values():
        node.destroy_publisher(pub)
    # one image in flight: replay plays the next one once features answered this one
    rep = launch('replay', str(bag), '--topics', '/camera/image_raw', '/camera/camera_info',
                 '--max-rate', '--answer', '/camera/image_raw:=/features/s_n',
                 '--wait-for-subscribers', '15', '--delay', '0.5')
    spin(120.0, until=lambda: rep.popen.poll() is not None)
    spin(0.5)  # what else comes (a copy would fail the comparison)
    # every image of the bag answered (exit 1 names any that was not), and an s_n for each
    assert rep.popen.wait(10) == 0, rep.log() + det.log() + feat.log()
    assert f'/camera/image_raw: {len(stamps)}' in rep.log(), rep.log()
    assert 'Traceback' not in det.log() + feat.log(), det.log() + feat.log()
    # after the last teach: the same messages, in the same order (of the images in the bag)
    after = [(st, m) for _, m in rec if (st := offline.header_ns(m.header)) > taught and
             st in images]
    live = [(st, m) for m in got if (st := offline.header_ns(m.header)) > taught]
    assert len(after) > 100
    assert [st for st, _ in live] == [st for st, _ in after]
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


def test_an_old_layout_bag_is_refused(tmp_path):
    """A bag whose features carry s* in ``velocity`` (before the desired topic): one line."""
    _images_only_bag(tmp_path / 'old')
    ts = bagio.typestore()
    T = ts.types
    with Writer(tmp_path / 'old2', version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conn = w.add_connection('/features/s_n', 'sensor_msgs/msg/JointState', typestore=ts)
        msg = T['sensor_msgs/msg/JointState'](
            header=T['std_msgs/msg/Header'](stamp=T['builtin_interfaces/msg/Time'](
                sec=1, nanosec=0), frame_id='c'),
            name=['s_nt_x', 's_nt_y', 's_nt_z', 'thetau_x', 'thetau_y', 'thetau_z'],
            position=np.ones(6), velocity=np.ones(6), effort=np.zeros(6))
        w.write(conn, 3, ts.serialize_cdr(msg, 'sensor_msgs/msg/JointState'))
        for topic, kind in (('/camera/camera_info', 'sensor_msgs/msg/CameraInfo'),
                            ('/camera/image_raw', 'sensor_msgs/msg/Image')):
            with bagio.bag(tmp_path / 'old') as reader:
                c = next(c for c in reader.connections if c.topic == topic)
                raw = next(r for _, _, r in bagio.iter_raw(reader, [c]))
            w.write(w.add_connection(topic, kind, typestore=ts), 1, raw)
    code, out, err = _run([str(tmp_path / 'old2')])
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 1 and len(lines) == 1 and 'old features layout' in lines[0], err


def test_regenerated_messages_are_written_as_exact_cdr():
    """What write_bag writes reads back the same with rclpy and with rosbags (strict)."""
    from geometry_msgs.msg import TwistStamped
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import JointState
    from sphere_servo.bag.compare import cdr
    from sphere_servo.ros.conversions import header, twist_from_array
    from sphere_servo.ros.vectors import features_msg, measurement_msg
    msgs = [(features_msg('s_n', header(1.5, 'camera_optical_frame'), np.arange(6.0) / 7),
             'sensor_msgs/msg/JointState'),
            (features_msg('s_cc', header(2.0, 'c')), 'sensor_msgs/msg/JointState'),
            (measurement_msg(None, header(3.0, 'c')), 'sensor_msgs/msg/JointState'),
            (TwistStamped(header=header(4.25, 'c'), twist=twist_from_array(np.arange(6.0))),
             'geometry_msgs/msg/TwistStamped')]
    for msg, msgtype in msgs:
        raw = cdr(msg, msgtype)
        assert deserialize_message(raw, type(msg)) == msg
        back = bagio.typestore().deserialize_cdr(raw, msgtype)
        assert (back.header.stamp.sec, back.header.stamp.nanosec, back.header.frame_id) == (
            msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id)
        if isinstance(msg, JointState):
            assert list(back.name) == list(msg.name)
            np.testing.assert_array_equal(back.position, np.asarray(msg.position))
