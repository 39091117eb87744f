"""
The recorder killed (SIGKILL) or interrupted (SIGINT) while 640×480 rgb8 images stream at 30 Hz.

SIGKILL: ``reindex`` recovers at least every image older than the commit window (0.5 s, plus
an allowance for delivery), counted by stamp against what this test published, and the
recovered bag replays. SIGINT: the recorder exits within 1 s; its bag holds every message
published well before the interrupt and none published after it (the publishers keep
publishing stamped messages through the interrupt).
"""
from __future__ import annotations

import array
import re
import signal
import subprocess
import threading
import time

from conftest import executable_path
import pytest

rclpy = pytest.importorskip('rclpy')
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402
from sensor_msgs.msg import Image  # noqa: E402
from sphere_servo.bag import bagio  # noqa: E402
from std_msgs.msg import String  # noqa: E402

W, H = 640, 480
IMAGES, TICKS = '/cam/image_raw', '/ticks'
COMMIT_WINDOW_S = 0.5   # record's default --commit-period
DELIVERY_S = 0.5        # allowance for an image to reach the recorder under load


class Streams:
    """Publishes stamped images (frame_id = index) and ticks (data = stamp) at given rates."""

    def __init__(self, node, ticks: bool = False):
        # 100 deep: more than Fast DDS's 3 s heartbeat at 30 Hz, so that a fragment lost on
        # the loaded localhost is repaired before the sample leaves the history
        reliable = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        self.img = node.create_publisher(Image, IMAGES, reliable)
        self.tick = node.create_publisher(String, TICKS, reliable) if ticks else None
        self.frames = [array.array('B', bytes([k]) * (W * H * 3)) for k in range(3)]
        self.sent: list[tuple[int, int]] = []      # (index, stamp ns) of each image
        self.ticks: list[int] = []                 # stamp ns of each tick

    def matched(self) -> bool:
        return all(p.get_subscription_count() > 0 for p in (self.img, self.tick) if p)

    def image(self) -> None:
        i = len(self.sent)
        msg = Image(height=H, width=W, encoding='rgb8', step=W * 3)
        t = time.time_ns()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(t, 1_000_000_000)
        msg.header.frame_id = str(i)
        msg.data = self.frames[i % 3]
        self.img.publish(msg)
        self.sent.append((i, t))

    def run(self, spin, seconds: float, hz: float = 30.0, tick_hz: float = 100.0,
            stop=None) -> None:
        """Publish for ``seconds`` (images at ``hz``, ticks at ``tick_hz``), spinning."""
        t0 = time.monotonic()
        n_img = n_tick = 0
        while time.monotonic() - t0 < seconds and not (stop and stop()):
            now = time.monotonic() - t0
            if now >= n_img / hz:
                self.image()
                n_img += 1
            if self.tick is not None and now >= n_tick / tick_hz:
                t = time.time_ns()
                self.tick.publish(String(data=str(t)))
                self.ticks.append(t)
                n_tick += 1
            spin(0.002)


def _start(launch, spin, out, storage, ticks=False):
    topics = [IMAGES, TICKS] if ticks else [IMAGES]
    rec = launch('record', '-o', str(out), '--storage', storage, '--topics', *topics)
    streams = Streams(spin.node, ticks)
    spin(20.0, until=lambda: streams.matched() and
         rec.log().count('subscribed to') == len(topics))
    assert streams.matched(), f'recorder never subscribed:\n{rec.log()}'
    spin(0.5)
    return rec, streams


def _images(bag) -> list[tuple[int, int]]:
    """(index, header stamp ns) of every image in a bag."""
    with bagio.bag(bag) as r:
        conns = bagio.select_connections(r, [IMAGES])
        out = []
        for c, _, raw in bagio.iter_raw(r, conns):
            m = r.deserialize(raw, c.msgtype)
            out.append((int(m.header.frame_id), m.header.stamp.sec * 10**9 +
                        m.header.stamp.nanosec))
    return out


@pytest.fixture
def spinner(test_node):
    node, spin = test_node
    spin.node = node
    return spin


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_sigkill_loses_at_most_the_commit_window(launch, spinner, ros_env, tmp_path, storage):
    out = tmp_path / 'bag'
    rec, streams = _start(launch, spinner, out, storage)
    streams.run(spinner, 5.0)
    t_kill = time.time_ns()
    rec.popen.kill()
    rec.popen.wait(10)
    streams.run(spinner, 0.3)  # the stream goes on, the recorder is gone
    with pytest.raises(bagio.BagError, match='reindex'):
        bagio.open_bag(out)
    p = subprocess.run([executable_path(ros_env, 'reindex'), str(out)], env=ros_env,
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stdout + p.stderr
    got = _images(out)
    ids = [i for i, _ in got]
    assert ids == list(range(len(ids))), ids  # a prefix of the stream: nothing skipped
    sent = dict(streams.sent)
    assert all(sent[i] == t for i, t in got)
    old = [i for i, t in streams.sent if t <= t_kill - (COMMIT_WINDOW_S + DELIVERY_S) * 1e9]
    lost_old = sorted(set(old) - set(ids))
    newest = max(t for _, t in got)
    print(f'{storage}: {len(ids)} of {len([1 for _, t in streams.sent if t <= t_kill])} '
          f'images published before the kill recovered; the newest recovered was published '
          f'{(t_kill - newest) / 1e9:.3f} s before it')
    assert len(old) > 100 and not lost_old, (len(old), lost_old[:5], p.stdout)
    # and the recovered bag plays (at its own rate, as recorded: a reliable keep-last
    # publisher outrunning its subscriber would drop samples at --max-rate)
    received = []
    spinner.node.create_subscription(Image, '/replayed', received.append,
                                     QoSProfile(depth=200,
                                                reliability=ReliabilityPolicy.RELIABLE),
                                     raw=True)
    rep = launch('replay', str(out), '--wait-for-subscribers', '20',
                 '--remap', f'{IMAGES}:=/replayed')
    spinner(90.0, until=lambda: rep.popen.poll() is not None and len(received) >= len(ids))
    assert rep.popen.wait(10) == 0, rep.log()
    assert len(received) == len(ids), rep.log()


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_sigint_stops_at_once_and_keeps_what_came_before(launch, spinner, tmp_path, storage):
    out = tmp_path / 'bag'
    rec, streams = _start(launch, spinner, out, storage, ticks=True)
    streams.run(spinner, 2.0)
    exited = {}

    def wait():
        rec.popen.wait(30)
        exited['t'] = time.monotonic()
    waiter = threading.Thread(target=wait)
    t_sig = time.time_ns()
    t0 = time.monotonic()
    rec.popen.send_signal(signal.SIGINT)
    waiter.start()
    streams.run(spinner, 1.5)  # keep publishing through the interrupt
    waiter.join(30)
    assert rec.popen.returncode == 0, rec.log()
    took = exited['t'] - t0
    print(f'{storage}: recorder exited {took:.3f} s after SIGINT')
    assert took < 1.0, f'took {took:.2f} s to stop\n{rec.log()}'
    before, after = t_sig - 0.3e9, t_sig + 0.1e9
    got = _images(out)
    ids = [i for i, _ in got]
    assert ids == list(range(len(ids))), ids
    assert all(t <= after for _, t in got), [t - t_sig for _, t in got if t > after]
    assert {i for i, t in streams.sent if t <= before} <= set(ids)
    with bagio.bag(out) as r:
        (c,) = bagio.select_connections(r, [TICKS])
        ticks = [int(r.deserialize(raw, c.msgtype).data) for _, _, raw in
                 bagio.iter_raw(r, [c])]
        total = bagio.summary(r)['message_count']
    assert ticks == streams.ticks[:len(ticks)]  # a prefix: every one up to the last
    assert ticks and max(ticks) <= after, (max(ticks) - t_sig) / 1e9
    assert [t for t in streams.ticks if t <= before] == ticks[:len(
        [t for t in streams.ticks if t <= before])]
    assert len(streams.sent) > len(ids) and len(streams.ticks) > len(ticks)  # more came
    m = re.search(r'wrote (\d+) messages', rec.log())
    assert m and int(m[1]) == total == len(ids) + len(ticks), rec.log()
