"""
rosbag2 recording and replay.

The installed ``record`` / ``replay`` executables against real DDS traffic from the test's
own node, and real rosbag2 files read back with rosbags.
"""
from __future__ import annotations

import array
import os
from pathlib import Path
import signal
import statistics
import subprocess
import time

from conftest import executable_path, wait_for
import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from rosbags.highlevel import AnyReader  # noqa: E402
from rosbags.rosbag2 import StoragePlugin, Writer  # noqa: E402
from rosbags.typesys import get_typestore, Stores  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image  # noqa: E402
from sphere_servo.bag import bagio  # noqa: E402
from std_msgs.msg import String  # noqa: E402
import yaml  # noqa: E402

TS = get_typestore(Stores.ROS2_JAZZY)
W, H = 640, 480
TOPICS = ['/camera/image_raw', '/camera/camera_info', '/servo/status']


def frame_bytes(i: int) -> bytes:
    """Make a 640×480 rgb8 frame that differs per index (and per pixel)."""
    row = (np.arange(W * 3, dtype=np.uint32) * 7 + i * 13) % 251
    img = (row[None, :] + np.arange(H, dtype=np.uint32)[:, None] * (i + 1)) % 256
    return img.astype(np.uint8).tobytes()


class Talker:
    """Publishers on the test node for an image, a latched camera_info and a status string."""

    def __init__(self, node):
        self.img = node.create_publisher(Image, TOPICS[0], 10)
        self.info = node.create_publisher(
            CameraInfo, TOPICS[1],
            QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self.status = node.create_publisher(String, TOPICS[2], QoSProfile(depth=10))
        self.sent = 0

    def matched(self) -> bool:
        return all(p.get_subscription_count() > 0 for p in (self.img, self.info, self.status))

    def publish(self, i: int) -> None:
        img = Image(height=H, width=W, encoding='rgb8', step=W * 3)
        img.header.frame_id = f'f{i}'
        img.header.stamp.sec, img.header.stamp.nanosec = 100 + i, 1000 * i
        img.data = array.array('B', frame_bytes(i))
        self.img.publish(img)
        self.info.publish(CameraInfo(width=W, height=H, distortion_model=f'plumb_bob{i}'))
        self.status.publish(String(data=f'status {i}'))
        self.sent = i + 1


def start_recording(launch, node, spin, out: Path, *extra: str):
    rec = launch('record', '-o', str(out), '--topics', *TOPICS, *extra)
    talker = Talker(node)
    spin(15.0, until=lambda: talker.matched() and rec.log().count('subscribed to') == 3)
    assert talker.matched(), f'recorder never subscribed:\n{rec.log()}'
    spin(0.3)
    return rec, talker


def publish_at(talker, spin, n: int, hz: float = 30.0, start: int = 0) -> None:
    t0 = time.monotonic()
    for i in range(start, start + n):
        talker.publish(i)
        spin(max(0.0, t0 + (i - start + 1) / hz - time.monotonic()))


def read_bag(path: Path) -> dict[str, list]:
    out: dict[str, list] = {t: [] for t in TOPICS}
    with AnyReader([path], default_typestore=TS) as reader:
        for conn, ts, raw in reader.messages():
            out[conn.topic].append((ts, reader.deserialize(raw, conn.msgtype)))
    return out


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_record_complete_bag(launch, test_node, tmp_path, storage):
    node, spin = test_node
    out = tmp_path / 'bag'
    rec, talker = start_recording(launch, node, spin, out, '--storage', storage)
    n = 45
    publish_at(talker, spin, n)
    spin(1.5)  # let the last messages arrive
    assert rec.stop() == 0, rec.log()
    assert 'Traceback' not in rec.log()

    meta = yaml.safe_load((out / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert meta['version'] == 9 and meta['storage_identifier'] == storage
    assert meta['message_count'] == 3 * n
    files = meta['relative_file_paths']
    assert len(files) == 1 and (out / files[0]).suffix == ('.mcap' if storage == 'mcap'
                                                           else '.db3')
    assert 1.0 < meta['duration']['nanoseconds'] / 1e9 < 4.0  # 44 gaps of 1/30 s
    topics = {t['topic_metadata']['name']: t for t in meta['topics_with_message_count']}
    assert set(topics) == set(TOPICS)
    types = {'/camera/image_raw': 'sensor_msgs/msg/Image',
             '/camera/camera_info': 'sensor_msgs/msg/CameraInfo',
             '/servo/status': 'std_msgs/msg/String'}
    for name, t in topics.items():
        assert t['message_count'] == n, f'{name} lost messages: {t["message_count"]} != {n}'
        assert t['topic_metadata']['type'] == types[name]
        assert t['topic_metadata']['type_description_hash'].startswith('RIHS01_')
        qos = t['topic_metadata']['offered_qos_profiles']
        assert len(qos) == 1 and qos[0]['reliability'] == 'reliable'
    assert topics['/camera/camera_info']['topic_metadata']['offered_qos_profiles'][0][
        'durability'] == 'transient_local'
    assert topics['/servo/status']['topic_metadata']['offered_qos_profiles'][0][
        'durability'] == 'volatile'

    msgs = read_bag(out)
    assert [m.header.frame_id for _, m in msgs['/camera/image_raw']] == \
        [f'f{i}' for i in range(n)]
    for i, (_, m) in enumerate(msgs['/camera/image_raw']):
        assert (m.width, m.height, m.encoding, m.step) == (W, H, 'rgb8', W * 3)
        assert (m.header.stamp.sec, m.header.stamp.nanosec) == (100 + i, 1000 * i)
        assert m.data.tobytes() == frame_bytes(i), f'image {i} payload differs'
    assert [m.data for _, m in msgs['/servo/status']] == [f'status {i}' for i in range(n)]
    assert [m.distortion_model for _, m in msgs['/camera/camera_info']] == \
        [f'plumb_bob{i}' for i in range(n)]
    stamps = [ts for ts, _ in msgs['/camera/image_raw']]
    assert stamps == sorted(stamps)
    # the offline reader of the replay pipeline decodes the same frames
    frames = list(bagio.iter_images(out, 'camera/image_raw'))
    assert len(frames) == n and frames[3][1].frame_id == 'f3'
    assert np.array_equal(frames[3][2], np.frombuffer(frame_bytes(3), np.uint8)
                          .reshape(H, W, 3))


def test_a_recorder_matched_late_gets_what_a_pipeline_writer_sent_before(
        launch, test_node, tmp_path):
    """
    The pipeline's stream writers (``qos.writer``) serve a late recorder their history.

    Under load a writer matches a new reader seconds after the reader counts it matched
    (a lost discovery message waits for a heartbeat): the launcher's teach image was sent
    in that gap and missed the bag. Here the gap is the whole time before the recorder
    starts: 5 frames sent then by a writer with the image topic's writer QoS are in the bag,
    with the 5 sent after, in order; the same 5 sent by a volatile writer of the readers'
    QoS (what the writers were) are not, and the 5 after are.
    """
    from sphere_servo.ros import qos
    node, spin = test_node
    tl = node.create_publisher(Image, '/camera/image_raw', qos.writer('camera/image_raw'))
    vol = node.create_publisher(Image, '/plain/image_raw', qos.TOPICS['camera/image_raw'])

    def send(i: int) -> None:
        img = Image(height=2, width=2, encoding='rgb8', step=6, data=bytes(range(i, i + 12)))
        img.header.frame_id = f'f{i}'
        tl.publish(img)
        vol.publish(img)
    for i in range(5):
        send(i)
        spin(0.02)
    spin(0.5)
    out = tmp_path / 'bag'
    rec = launch('record', '-o', str(out), '--topics', '/camera/image_raw', '/plain/image_raw')
    spin(15.0, until=lambda: tl.get_subscription_count() > 0 and vol.get_subscription_count() > 0
         and rec.log().count('subscribed to') == 2)
    assert vol.get_subscription_count() > 0, rec.log()
    spin(1.0)
    for i in range(5, 10):
        send(i)
        spin(0.05)
    spin(1.5)
    assert rec.stop() == 0, rec.log()
    got = {t: [] for t in ('/camera/image_raw', '/plain/image_raw')}
    with AnyReader([out], default_typestore=TS) as reader:
        for conn, _, raw in reader.messages():
            got[conn.topic].append(reader.deserialize(raw, conn.msgtype).header.frame_id)
    assert got['/camera/image_raw'] == [f'f{i}' for i in range(10)], rec.log()
    assert got['/plain/image_raw'] == [f'f{i}' for i in range(5, 10)], rec.log()


@pytest.mark.parametrize('sig,storage', [(signal.SIGINT, 'mcap'),
                                         (signal.SIGTERM, 'sqlite3')])
def test_interrupted_recording_is_readable(launch, test_node, tmp_path, sig, storage):
    node, spin = test_node
    out = tmp_path / 'bag'
    rec, talker = start_recording(launch, node, spin, out, '--storage', storage,
                                  '--compression', 'zstd')
    publish_at(talker, spin, 20)
    rec.popen.send_signal(sig)          # mid-stream: keep publishing while it stops
    publish_at(talker, spin, 15, start=20)
    rec.popen.wait(15)
    assert rec.popen.returncode == 0, rec.log()
    assert 'Traceback' not in rec.log()
    msgs = read_bag(out)
    ids = [int(m.header.frame_id[1:]) for _, m in msgs['/camera/image_raw']]
    assert len(ids) >= 15 and ids == list(range(len(ids))), ids
    # everything it received is in the bag: its own summary matches the file
    assert f'/camera/image_raw: {len(ids)}' in rec.log()
    meta = yaml.safe_load((out / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert meta['message_count'] == sum(len(v) for v in msgs.values())
    assert msgs['/camera/image_raw'][-1][1].data.tobytes() == frame_bytes(ids[-1])
    data = next(out.glob('*.mcap' if storage == 'mcap' else '*.db3')).stat().st_size
    assert data < len(ids) * W * H * 3 / 2, 'zstd compression was not applied'
    if storage == 'sqlite3':  # per-message compression is declared in metadata.yaml
        assert (meta['compression_mode'], meta['compression_format']) == ('message', 'zstd')


def test_interrupt_first_drains_what_arrived(launch, test_node, tmp_path):
    """
    A recorder that is behind when Ctrl-C comes drains its subscriptions before closing.

    Here it is stopped with SIGSTOP while a burst is published, then woken with SIGINT
    pending: it takes what its subscriptions already hold before it closes the bag, so the
    whole burst is in it. Fast DDS may drop what it sends to a stopped process (its
    shared-memory port looks dead to the sender) and repair it only at the writer's next
    heartbeat (3 s), after the drain: so up to three recorders, each one's bag holding only
    messages of the burst, in order, once each, and one of them the whole burst.
    """
    from std_srvs.srv import Trigger
    node, spin = test_node
    pub = node.create_publisher(String, '/burst', QoSProfile(
        depth=200, reliability=ReliabilityPolicy.RELIABLE))
    ready = node.create_client(Trigger, '/recorder/ready')

    def is_ready() -> bool:
        fut = ready.call_async(Trigger.Request())
        return spin(10.0, until=fut.done) and fut.result().success
    burst = [str(i) for i in range(80)]
    attempts = []
    for attempt in range(3):
        out = tmp_path / f'bag{attempt}'
        rec = launch('record', '-o', str(out), '--topics', '/burst')
        # matched on the recorder's side too (its ready service), not only on the writer's:
        # a sample reaching a reader before it knows the writer is dropped and repaired late
        assert spin(15.0, until=lambda: pub.get_subscription_count() > 0
                    and ready.service_is_ready()), rec.log()
        wait_for(is_ready, 20.0, what='the recorder to match the writer')
        rec.popen.send_signal(signal.SIGSTOP)
        try:
            for m in burst:
                pub.publish(String(data=m))
            spin(0.3)
            rec.popen.send_signal(signal.SIGINT)
        finally:
            rec.popen.send_signal(signal.SIGCONT)
        # keep our writer alive for the reliable resends while the recorder drains
        spin(15.0, until=lambda: rec.popen.poll() is not None)
        code = rec.popen.wait(15)
        with AnyReader([out], default_typestore=TS) as reader:
            got = [reader.deserialize(raw, c.msgtype).data for c, _, raw in reader.messages()]
        assert code == (0 if got else 1), rec.log()  # exit 1: it recorded nothing
        assert [int(m) for m in got] == sorted({int(m) for m in got}) and set(got) <= set(burst)
        attempts.append(len(got))
        if got == burst:
            break
        spin(3.5)  # the repairs of this burst reach no recorder now
    assert attempts[-1] == len(burst), (attempts, rec.log())


def test_ready_service_names_what_is_not_recorded_yet(launch, test_node, tmp_path):
    """
    ``/recorder/ready`` (the launcher waits for it before a run) says what is missing.

    Not ready while a topic has no publisher, or while a publisher is not matched (a
    best-effort one that appeared after the recorder subscribed reliably); ready once every
    topic is matched.
    """
    from std_srvs.srv import Trigger
    node, spin = test_node
    rec = launch('record', '-o', str(tmp_path / 'bag'), '--topics', *TOPICS)
    cli = node.create_client(Trigger, '/recorder/ready')
    assert spin(20.0, until=cli.service_is_ready), rec.log()

    def ask():
        fut = cli.call_async(Trigger.Request())
        assert spin(10.0, until=fut.done), rec.log()
        return fut.result()

    first = ask()
    assert not first.success and all(t in first.message for t in TOPICS), first.message
    img = node.create_publisher(Image, TOPICS[0], 10)
    wait_for(lambda: (spin(0.1), TOPICS[0] not in ask().message)[1], 20.0,
             what='the recorder to match the image topic')
    partial = ask()
    assert not partial.success and TOPICS[1] in partial.message, partial.message
    talker = Talker(node)
    wait_for(lambda: (spin(0.1), ask().success)[1], 20.0, what='the recorder to be ready')
    assert ask().message == 'recording 3 topics' and talker.matched() and img
    late = node.create_publisher(String, TOPICS[2], QoSProfile(
        depth=10, reliability=ReliabilityPolicy.BEST_EFFORT))
    wait_for(lambda: (spin(0.1), not ask().success)[1], 20.0,
             what='the recorder to see the unmatched publisher')
    assert f'{TOPICS[2]} (not matched with every publisher yet)' in ask().message
    talker.publish(0)  # a recorder that recorded nothing exits 1 (the test below)
    spin(1.0)
    assert late and rec.stop() == 0, rec.log()


@pytest.mark.parametrize('publisher', [False, True], ids=['no publisher', 'silent publisher'])
def test_a_recording_of_nothing_exits_1_and_says_why(launch, test_node, tmp_path, publisher):
    """
    A recorder that wrote no message did nothing: exit 1, naming what it had subscribed to.

    With no publisher of the topic it never subscribed; with one that never publishes, it
    subscribed and nothing came. The empty bag is left, valid, for the record.
    """
    node, spin = test_node
    out = tmp_path / 'bag'
    rec = launch('record', '-o', str(out), '--topics', '/nothing_here')
    if publisher:
        pub = node.create_publisher(String, '/nothing_here', QoSProfile(depth=10))
        assert spin(20.0, until=lambda: pub.get_subscription_count() > 0), rec.log()
    else:
        assert spin(20.0, until=lambda: 'recording to' in rec.log()), rec.log()
    spin(0.5)
    assert rec.stop() == 1, rec.log()
    log = rec.log()
    assert 'no message was recorded' in log
    assert ('subscribed to /nothing_here' in log) is publisher, log
    with AnyReader([out], default_typestore=TS) as reader:
        assert reader.message_count == 0


def test_idle_service_says_when_nothing_new_came(launch, test_node, tmp_path):
    """
    ``/recorder/idle`` succeeds once nothing new has arrived for ``--idle-quiet`` s.

    A supervisor stopping a run waits for it before interrupting the recorder, which then
    stops at once. A byte-identical repeat of a topic's last message is not new (an idle
    lockstep arm_sim re-publishes).
    """
    from std_srvs.srv import Trigger
    node, spin = test_node
    rec = launch('record', '-o', str(tmp_path / 'bag'), '--topics', '/idle_test',
                 '--idle-quiet', '1.0')
    pub = node.create_publisher(String, '/idle_test', QoSProfile(depth=10))
    cli = node.create_client(Trigger, '/recorder/idle')
    assert spin(20.0, until=lambda: cli.service_is_ready() and
                pub.get_subscription_count() > 0), rec.log()

    def ask():
        fut = cli.call_async(Trigger.Request())
        assert spin(10.0, until=fut.done), rec.log()
        return fut.result()

    for i in range(30):  # 1.5 s of news
        pub.publish(String(data=f'n{i}'))
        spin(0.05)
    busy = ask()
    assert not busy.success and busy.message.startswith('nothing new for 0.'), busy.message
    spin(1.3)
    assert ask().success
    pub.publish(String(data='n29'))  # a repeat of the last one
    spin(0.3)
    assert ask().success
    pub.publish(String(data='news'))
    spin(0.3)
    late = ask()
    assert not late.success, late.message
    assert rec.stop() == 0, rec.log()


def write_timing_bag(path: Path, storage: StoragePlugin) -> list[int]:
    """Write a bag with irregular gaps (20–70 ms) on /chatter; return its timestamps."""
    t, stamps = 1_700_000_000_000_000_000, []
    with Writer(path, version=9, storage_plugin=storage) as w:
        conn = w.add_connection('/chatter', 'std_msgs/msg/String', typestore=TS)
        for i in range(40):
            w.write(conn, t, TS.serialize_cdr(TS.types['std_msgs/msg/String'](data=str(i)),
                                              'std_msgs/msg/String'))
            stamps.append(t)
            t += (20 + (i * 37) % 51) * 1_000_000
    return stamps


def replay_and_receive(launch, node, spin, bag: Path, topic: str, *args: str):
    got: list[tuple[int, str]] = []
    clock: list[int] = []
    from rosgraph_msgs.msg import Clock
    node.create_subscription(
        String, topic, lambda m, info: got.append((info['received_timestamp'], m.data)),
        QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))
    node.create_subscription(Clock, '/clock',
                             lambda m: clock.append(m.clock.sec * 10**9 + m.clock.nanosec),
                             QoSProfile(depth=100))
    proc = launch('replay', str(bag), '--wait-for-subscribers', '15', '--delay', '0.3', *args)
    spin(30.0, until=lambda: proc.popen.poll() is not None and len(got) >= 40)
    spin(0.2)
    assert proc.popen.wait(10) == 0, proc.log()
    assert [d for _, d in got] == [str(i) for i in range(40)], proc.log()
    return [t for t, _ in got], clock


def test_replay_timing_rate_1(launch, test_node, tmp_path):
    node, spin = test_node
    stamps = write_timing_bag(tmp_path / 'bag', StoragePlugin.MCAP)
    recv, _ = replay_and_receive(launch, node, spin, tmp_path / 'bag', '/chatter',
                                 '--topics', 'chatter')
    bag_gaps = np.diff(stamps) / 1e6
    recv_gaps = np.diff(recv) / 1e6
    err = np.abs(recv_gaps - bag_gaps)
    assert statistics.median(err) < 5.0, (bag_gaps, recv_gaps)


def test_replay_rate_2_clock_remap_sqlite(launch, test_node, tmp_path):
    node, spin = test_node
    stamps = write_timing_bag(tmp_path / 'bag', StoragePlugin.SQLITE3)
    recv, clock = replay_and_receive(launch, node, spin, tmp_path / 'bag', '/replayed',
                                     '--rate', '2.0', '--clock', '100',
                                     '--remap', 'chatter:=/replayed')
    bag_span, recv_span = (stamps[-1] - stamps[0]) / 1e9, (recv[-1] - recv[0]) / 1e9
    assert abs(recv_span - bag_span / 2) < 0.15 * bag_span / 2, (bag_span, recv_span)
    err = np.abs(np.diff(recv) / 1e6 - np.diff(stamps) / 2e6)
    assert statistics.median(err) < 5.0
    # /clock follows bag time and never goes back
    assert len(clock) >= 40 and clock == sorted(clock)
    assert stamps[0] <= clock[0] and clock[-1] == stamps[-1]


# --- bad input: one-line error, non-zero exit, no traceback -------------------------------

def _images_bag(path: Path, storage: StoragePlugin, n: int = 8) -> None:
    with Writer(path, version=9, storage_plugin=storage) as w:
        conn = w.add_connection('/camera/image_raw', 'sensor_msgs/msg/Image', typestore=TS)
        Img, Hdr = TS.types['sensor_msgs/msg/Image'], TS.types['std_msgs/msg/Header']
        Time = TS.types['builtin_interfaces/msg/Time']
        for i in range(n):
            msg = Img(header=Hdr(stamp=Time(sec=i, nanosec=0), frame_id='c'), height=H,
                      width=W, encoding='rgb8', is_bigendian=0, step=W * 3,
                      data=np.frombuffer(frame_bytes(i), np.uint8))
            w.write(conn, (i + 1) * 33_000_000, TS.serialize_cdr(msg, 'sensor_msgs/msg/Image'))


def _truncate(bag: Path, suffix: str) -> None:
    f = next(bag.glob(f'*{suffix}'))
    os.truncate(f, f.stat().st_size // 2)


def _bad_cases(tmp: Path) -> dict[str, list[str]]:
    (tmp / 'notabag').mkdir()
    (tmp / 'notabag' / 'x.txt').write_text('hello')
    _images_bag(tmp / 'trunc_mcap', StoragePlugin.MCAP)
    _truncate(tmp / 'trunc_mcap', '.mcap')
    _images_bag(tmp / 'trunc_db3', StoragePlugin.SQLITE3)
    _truncate(tmp / 'trunc_db3', '.db3')
    _images_bag(tmp / 'good', StoragePlugin.MCAP, n=2)
    return {
        'missing path': ['replay', str(tmp / 'nope')],
        'not a bag': ['replay', str(tmp / 'notabag')],
        'truncated mcap': ['replay', str(tmp / 'trunc_mcap'), '--max-rate'],
        'truncated db3': ['replay', str(tmp / 'trunc_db3'), '--max-rate'],
        'unknown topic': ['replay', str(tmp / 'good'), '--topics', '/no/such/topic'],
        'existing output': ['record', '-o', str(tmp / 'good')],
    }


def test_bad_inputs(ros_env, tmp_path):
    cases = _bad_cases(tmp_path)
    procs = {what: subprocess.Popen([executable_path(ros_env, cmd[0]), *cmd[1:]], env=ros_env,
                                    stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for what, cmd in cases.items()}
    for what, p in procs.items():
        try:
            out, err = p.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            p.kill()
            pytest.fail(f'{what}: did not exit')
        lines = [ln for ln in err.splitlines() if ln.strip()]
        assert p.returncode != 0, f'{what}: exit 0\n{out}{err}'
        assert 'Traceback' not in out + err, f'{what}:\n{err}'
        assert len(lines) == 1 and 'error:' in lines[0], f'{what}: {err!r}'
    assert not (tmp_path / 'good' / 'good.mcap.tmp').exists()


def test_bagio_errors_without_ros(tmp_path):
    cases = _bad_cases(tmp_path)
    for what in ('missing path', 'not a bag', 'truncated mcap', 'truncated db3'):
        with pytest.raises(bagio.BagError):
            with bagio.bag(cases[what][1]) as reader:
                for _ in bagio.iter_raw(reader):
                    pass
    with bagio.bag(tmp_path / 'good') as reader:
        with pytest.raises(bagio.BagError, match='not in bag'):
            bagio.select_connections(reader, ['/no/such/topic'])
        s = bagio.summary(reader)
    assert s['storage'] == 'mcap' and s['message_count'] == 2
    assert s['topics'] == [{'name': '/camera/image_raw', 'type': 'sensor_msgs/msg/Image',
                            'count': 2, 'qos': []}]
    with pytest.raises(bagio.BagError, match='exists already'):
        bagio.check_new_output(tmp_path / 'good')


def test_older_bag_format_and_its_qos(tmp_path):
    """
    A version-8 bag is read, and replay offers the recorded publisher's QoS.

    Version 8 stores the QoS as a YAML string, as Humble/Iron's ros2 bag writes it.
    """
    from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness,
                                    QosReliability)

    from sphere_servo.bag.replay import publisher_qos
    inf = bagio.qos_time(bagio.INFINITE_NS)
    qos = Qos(QosHistory.KEEP_LAST, 1, QosReliability.BEST_EFFORT,
              QosDurability.TRANSIENT_LOCAL, inf, inf, QosLiveliness.AUTOMATIC, inf, False)
    with Writer(tmp_path / 'v8', version=8, storage_plugin=StoragePlugin.SQLITE3) as w:
        conn = w.add_connection('/camera/camera_info', 'sensor_msgs/msg/CameraInfo',
                                typestore=TS, offered_qos_profiles=[qos])
        msg = TS.types['sensor_msgs/msg/CameraInfo'](
            header=TS.types['std_msgs/msg/Header'](
                stamp=TS.types['builtin_interfaces/msg/Time'](sec=1, nanosec=2), frame_id='c'),
            height=H, width=W, distortion_model='plumb_bob', d=np.zeros(5), k=np.eye(3).ravel(),
            r=np.eye(3).ravel(), p=np.zeros(12), binning_x=0, binning_y=0,
            roi=TS.types['sensor_msgs/msg/RegionOfInterest'](
                x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))
        w.write(conn, 5, TS.serialize_cdr(msg, 'sensor_msgs/msg/CameraInfo'))
    meta = yaml.safe_load((tmp_path / 'v8' / 'metadata.yaml').read_text())
    assert isinstance(meta['rosbag2_bagfile_information']['topics_with_message_count'][0][
        'topic_metadata']['offered_qos_profiles'], str)
    with bagio.bag(tmp_path / 'v8') as reader:
        s = bagio.summary(reader)
        (conn,) = bagio.select_connections(reader, ['camera/camera_info'])
        p = publisher_qos(conn)
        assert len(list(bagio.iter_raw(reader))) == 1
    assert s['version'] == 8 and s['topics'][0]['qos'][0]['durability'] == 'transient_local'
    assert s['topics'][0]['qos'][0]['deadline'] == {'sec': 9223372036, 'nsec': 854775807}
    assert p.reliability == ReliabilityPolicy.BEST_EFFORT
    assert p.durability == DurabilityPolicy.TRANSIENT_LOCAL
