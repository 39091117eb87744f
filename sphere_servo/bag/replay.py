"""
replay: republish a rosbag2 (MCAP or sqlite3, ours or one by ``ros2 bag record``).

    ros2 run sphere_servo replay BAG [--topics T ...] [--rate R | --max-rate] [--loop]
                                 [--clock [HZ]] [--remap OLD:=NEW ...] [--delay S]
                                 [--wait-for-subscribers [S]]

Messages are republished as their serialized bytes (never deserialized), with the bag's
timing scaled by ``--rate``, on publishers with the QoS the recording publishers offered.
``--clock`` publishes ``/clock`` from bag time (at HZ, default 40, and before each message),
so nodes with ``use_sim_time`` follow the bag.
"""
from __future__ import annotations

import argparse
import sys
import time

from sphere_servo.bag.bagio import BagError, iter_raw, open_bag, select_connections, \
    topic_name


def parse_args(argv: list[str]) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog='replay', description=__doc__.split('\n\n')[0])
    p.add_argument('bag', help='rosbag2 directory (with metadata.yaml)')
    p.add_argument('--topics', nargs='+', default=None, metavar='TOPIC',
                   help='topics to replay (default: all)')
    g = p.add_mutually_exclusive_group()
    g.add_argument('-r', '--rate', type=float, default=1.0, help='time factor (default 1.0)')
    g.add_argument('--max-rate', action='store_true', help='publish as fast as possible')
    p.add_argument('-l', '--loop', action='store_true', help='replay again and again')
    p.add_argument('--clock', nargs='?', type=float, const=40.0, default=None, metavar='HZ',
                   help='publish /clock from bag time (default 40 Hz)')
    p.add_argument('--remap', nargs='+', default=[], metavar='OLD:=NEW',
                   help='publish topic OLD of the bag on NEW')
    p.add_argument('--delay', type=float, default=0.0, help='seconds to wait before playing')
    p.add_argument('--wait-for-subscribers', nargs='?', type=float, const=10.0, default=None,
                   metavar='S', help='wait (at most S s, default 10) until every publisher '
                   'has a subscriber')
    opts = p.parse_args(argv)
    if not opts.max_rate and not opts.rate > 0:
        p.error('--rate must be > 0')
    if opts.clock is not None and not opts.clock > 0:
        p.error('--clock frequency must be > 0')
    return opts


def split_ros_args(args: list[str]) -> tuple[list[str], list[str]]:
    """
    Split ``args`` into (our arguments, the ``--ros-args ... [--]`` sections).

    Unlike ``remove_ros_args`` this keeps ``OLD:=NEW`` words, which rcl would take for
    (deprecated) global remap rules.
    """
    ours, ros = [], []
    it = iter(args)
    for a in it:
        if a == '--ros-args':
            ros.append(a)
            for b in it:
                if b == '--':
                    break
                ros.append(b)
            else:
                break
            ros.append('--')
        else:
            ours.append(a)
    return ours, ros


def parse_remaps(remaps: list[str]) -> dict[str, str]:
    out = {}
    for r in remaps:
        old, sep, new = r.partition(':=')
        if not sep or not old.strip() or not new.strip():
            raise BagError(f'bad remap {r!r}: expected OLD:=NEW')
        out[topic_name(old)] = topic_name(new)
    return out


def publisher_qos(conn):
    """Return the QoS of the recording's first publisher (as ros2 bag play), keep-last ≥ 100."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    offered = getattr(conn.ext, 'offered_qos_profiles', None) or []
    qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                     reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.VOLATILE)
    if offered:
        o = offered[0]
        if o.reliability.name == 'BEST_EFFORT':
            qos.reliability = ReliabilityPolicy.BEST_EFFORT
        if o.durability.name == 'TRANSIENT_LOCAL':
            qos.durability = DurabilityPolicy.TRANSIENT_LOCAL
        qos.depth = max(100, o.depth)
    return qos


class Player:
    """Publishes ``(connection, t, raw)`` from a bag with scaled timing."""

    def __init__(self, node, reader, conns, opts, remaps):
        from rclpy.qos import QoSProfile
        from rosgraph_msgs.msg import Clock

        from sphere_servo.bag.record import import_message
        self.node, self.reader, self.conns, self.opts = node, reader, conns, opts
        self.pubs = {}
        self.counts: dict[str, int] = {}
        for c in conns:
            name = remaps.get(c.topic, c.topic)
            try:
                cls = import_message(c.msgtype)
            except (ImportError, AttributeError, ValueError):
                raise BagError(f'cannot import message type {c.msgtype} of {c.topic}') \
                    from None
            if name not in self.pubs:
                self.pubs[name] = node.create_publisher(cls, name, publisher_qos(c))
                self.counts[name] = 0
        self.topic_of = {c.id: remaps.get(c.topic, c.topic) for c in conns}
        self.Clock = Clock
        self.clock_pub = node.create_publisher(Clock, '/clock', QoSProfile(depth=10)) \
            if opts.clock else None
        self.clock_period = 1.0 / opts.clock if opts.clock else None

    def publish_clock(self, bag_ns: int) -> None:
        msg = self.Clock()
        msg.clock.sec, msg.clock.nanosec = divmod(int(bag_ns), 1_000_000_000)
        self.clock_pub.publish(msg)

    def wait_until(self, target: float, bag_at) -> None:
        """Sleep until monotonic ``target``, publishing /clock meanwhile."""
        while True:
            now = time.monotonic()
            if now >= target:
                return
            step = target - now
            if self.clock_pub is not None:
                if now >= self.next_clock:
                    self.publish_clock(bag_at(now))
                    self.next_clock = now + self.clock_period
                step = min(step, max(0.0, self.next_clock - now))
            time.sleep(step)

    def play_once(self) -> int:
        """One pass over the bag; returns how many messages it published."""
        import rclpy
        sent = 0
        rate = None if self.opts.max_rate else self.opts.rate
        t0_bag = None
        t0_wall = None
        self.next_clock = time.monotonic()
        for conn, ts, raw in iter_raw(self.reader, self.conns):
            if not rclpy.ok():  # SIGTERM shut the context down
                break
            if t0_bag is None:
                t0_bag, t0_wall = ts, time.monotonic()
            if rate is not None:
                self.wait_until(t0_wall + (ts - t0_bag) / 1e9 / rate,
                                lambda now: t0_bag + int((now - t0_wall) * rate * 1e9))
            if self.clock_pub is not None:
                self.publish_clock(ts)
            topic = self.topic_of[conn.id]
            self.pubs[topic].publish(raw)
            self.counts[topic] += 1
            sent += 1
        return sent

    def flush(self, timeout: float = 3.0) -> None:
        """
        Wait until reliable subscribers acknowledged what was published.

        Then the last messages are not lost when the process exits right after publishing.
        """
        from rclpy.duration import Duration
        deadline = time.monotonic() + timeout
        for p in [*self.pubs.values(), self.clock_pub]:
            if p is not None:
                p.wait_for_all_acked(Duration(seconds=max(0.0, deadline - time.monotonic())))

    def wait_for_subscribers(self, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if all(p.get_subscription_count() > 0 for p in self.pubs.values()):
                return True
            time.sleep(0.05)
        return False


def main(args=None) -> int:
    import rclpy
    from rclpy.executors import ExternalShutdownException
    full = list(sys.argv if args is None else args)
    ours, ros_args = split_ros_args(full[1:])
    opts = parse_args(ours)
    try:
        remaps = parse_remaps(opts.remap)
        reader = open_bag(opts.bag)
    except BagError as err:
        print(f'replay: error: {err}', file=sys.stderr)
        return 1

    rclpy.init(args=full[:1] + ros_args)
    node = None
    player = None
    code = 0
    started = time.monotonic()
    try:
        conns = select_connections(reader, opts.topics)
        node = rclpy.create_node('replay')
        player = Player(node, reader, conns, opts, remaps)
        if opts.wait_for_subscribers is not None and \
                not player.wait_for_subscribers(opts.wait_for_subscribers):
            print('replay: warning: not every topic has a subscriber; playing anyway',
                  file=sys.stderr, flush=True)
        if opts.delay > 0:
            time.sleep(opts.delay)
        print(f'replay: playing {opts.bag} ({len(conns)} topics)', flush=True)
        started = time.monotonic()
        while True:
            sent = player.play_once()
            if not opts.loop or not rclpy.ok() or sent == 0:
                break
        player.flush()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except BagError as err:
        print(f'replay: error: {err}', file=sys.stderr)
        code = 1
    except Exception as err:  # e.g. publishing after an external shutdown
        if rclpy.ok():
            print(f'replay: error: {type(err).__name__}: {" ".join(str(err).split())}',
                  file=sys.stderr)
            code = 1
    finally:
        reader.close()
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    if player is not None:
        elapsed = time.monotonic() - started
        total = sum(player.counts.values())
        print(f'replay: published {total} messages in {elapsed:.3f} s '
              f'({total / elapsed if elapsed > 0 else 0:.1f} msg/s)')
        for name, n in sorted(player.counts.items()):
            print(f'  {name}: {n}')
    return code


if __name__ == '__main__':
    sys.exit(main())
