"""
record: write live topics into a rosbag2 (MCAP or sqlite3) with the ``rosbags`` library.

    ros2 run sphere_servo record [-o OUT] [--storage mcap|sqlite3] [--compression zstd]
                                 [--topics T ...] [--all] [--duration S] [--qos-depth N]

Topics are subscribed raw (serialized CDR, never deserialized) as soon as they appear in the
graph with a publisher; each message is stamped with its receive time (the node clock when
``use_sim_time`` is set) and written by a writer thread, so the executor only queues bytes.
The service ``/recorder/ready`` (std_srvs/Trigger) answers success once every topic asked for
is subscribed and matched with each of its publishers (the launcher waits for it before the
run begins: under load, discovering a node's topics can take seconds); otherwise its message
names what is still missing.
The publishers' offered QoS profiles go into metadata.yaml as ``ros2 bag`` writes them
(rosbag2 format version 9, as Jazzy). Ctrl-C / SIGTERM / ``--duration`` close the bag
properly: it holds everything received before the interrupt.
"""
from __future__ import annotations

import argparse
from datetime import datetime
import importlib
import queue
import signal
import sys
import threading
import time

from sphere_servo.bag.bagio import BagError, check_new_output, qos_time, topic_name, typestore

# the pipeline's topics (module docstrings of ros/arm_sim, detector, features, servo):
# enough to regenerate the features offline (``refeatures``) and to compare with what ran
DEFAULT_TOPICS = ['camera/image_raw', 'camera/camera_info', 'detector/measurement',
                  'features/s_n', 'features/s_n/desired', 'camera/cmd_vel', 'servo/state',
                  'ground_truth/camera_pose', 'joint_states', 'arm_sim/state', '/diagnostics']
# never recorded by --all (as ros2 bag record --all)
EXCLUDED = {'/rosout', '/parameter_events'}


def parse_args(argv: list[str]) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog='record', description=__doc__.split('\n\n')[0])
    p.add_argument('-o', '--output', default=None,
                   help='bag directory to create (must not exist); '
                        'default rosbag2_YYYY_MM_DD-HH_MM_SS')
    p.add_argument('-s', '--storage', choices=['mcap', 'sqlite3'], default='mcap')
    p.add_argument('--compression', choices=['none', 'zstd'], default='none',
                   help='zstd: MCAP chunk compression (sqlite3: per message)')
    p.add_argument('--topics', nargs='+', default=None, metavar='TOPIC',
                   help=f'topics to record (default: {" ".join(DEFAULT_TOPICS)})')
    p.add_argument('-a', '--all', action='store_true', help='record every topic that appears')
    p.add_argument('--duration', type=float, default=None,
                   help='stop after this many seconds (default: until Ctrl-C)')
    p.add_argument('--qos-depth', type=int, default=100,
                   help='history depth of the recording subscriptions (default 100)')
    return p.parse_args(argv)


def import_message(msgtype: str):
    """Import the rclpy message class of ``pkg/msg/Type``."""
    try:
        from rosidl_runtime_py.utilities import get_message
        return get_message(msgtype)
    except ImportError:
        pass
    pkg, kind, name = msgtype.split('/')
    return getattr(importlib.import_module(f'{pkg}.{kind}'), name)


def to_bag_qos(profile):
    """Convert an rclpy QoSProfile (as offered by a publisher) to a rosbags Qos for metadata."""
    from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness,
                                    QosReliability)

    def ns(d):
        return getattr(d, 'nanoseconds', d)

    return Qos(QosHistory(int(profile.history)), int(profile.depth),
               QosReliability(int(profile.reliability)), QosDurability(int(profile.durability)),
               qos_time(ns(profile.deadline)), qos_time(ns(profile.lifespan)),
               QosLiveliness(int(profile.liveliness)),
               qos_time(ns(profile.liveliness_lease_duration)),
               bool(profile.avoid_ros_namespace_conventions))


def subscription_qos(offered: list, depth: int):
    """
    Return the QoS ros2 bag adapts to its publishers, keep-last ``depth``.

    Reliable / transient-local only when all publishers offer it (so every publisher is
    matched).
    """
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    reliable = all(q.reliability == ReliabilityPolicy.RELIABLE for q in offered)
    latched = all(q.durability == DurabilityPolicy.TRANSIENT_LOCAL for q in offered)
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=depth,
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)


class _Topic:
    """A topic's connection in the bag, bound by the writer thread."""

    __slots__ = ('name', 'conn')

    def __init__(self, name: str):
        self.name, self.conn = name, None


class BagSink:
    """
    A rosbags Writer owned by one thread (sqlite3 objects stay in the thread that made them).

    The thread opens the bag, adds connections and writes messages from a FIFO queue, so
    the executor only queues bytes; ``close()`` drains the queue and closes the bag.
    """

    def __init__(self, writer):
        self.writer = writer
        self.queue: queue.SimpleQueue = queue.SimpleQueue()
        self.counts: dict[str, int] = {}
        self.received = 0  # messages queued so far (the executor's side)
        self.fresh = 0     # of those, not a byte-identical repeat of the topic's previous one
        self._prev: dict[str, bytes] = {}
        self.error: BaseException | None = None
        self._opened = threading.Event()
        self.thread = threading.Thread(target=self._run, name='bag-writer', daemon=True)
        self.thread.start()
        self._opened.wait()
        if self.error is not None:
            raise self.error

    def add_connection(self, topic: str, msgtype: str, offered: list) -> _Topic:
        handle = _Topic(topic)
        self.counts[topic] = 0
        self.queue.put(('add', handle, msgtype, offered))
        return handle

    def put(self, handle: _Topic, stamp_ns: int, data: bytes) -> None:
        self.received += 1
        if self._prev.get(handle.name) != data:  # (an idle lockstep arm_sim re-publishes)
            self.fresh += 1
            self._prev[handle.name] = data
        self.queue.put((handle, stamp_ns, data))

    def _run(self) -> None:
        try:
            self.writer.open()
        except BaseException as err:
            self.error = err
            self._opened.set()
            return
        self._opened.set()
        while True:
            item = self.queue.get()
            if item is None:
                break
            try:
                if item[0] == 'add':
                    _, handle, msgtype, offered = item
                    handle.conn = self.writer.add_connection(
                        handle.name, msgtype, typestore=typestore(),
                        offered_qos_profiles=offered)
                    continue
                handle, stamp, data = item
                if handle.conn is not None:
                    self.writer.write(handle.conn, stamp, data)
                    self.counts[handle.name] += 1
            except Exception as err:  # keep draining; reported at exit
                self.error = err
        try:
            self.writer.close()
        except Exception as err:
            self.error = err

    def close(self) -> None:
        self.queue.put(None)
        self.thread.join()


def make_recorder(sink: BagSink, topics: list[str] | None, all_topics: bool, depth: int):
    from rclpy.node import Node

    class Recorder(Node):

        def __init__(self):
            super().__init__('recorder')
            self.sink = sink
            self.wanted = {topic_name(t) for t in (topics or [])}
            self.all_topics = all_topics
            self.subs: dict[str, object] = {}
            self.skipped: set[str] = set()
            self.sim_time = self.get_parameter('use_sim_time').value
            self.clock_ = self.get_clock()
            self.discover()
            missing = sorted(self.wanted - set(self.subs))
            if missing:
                print(f'record: waiting for {", ".join(missing)}', flush=True)
            self.timer = self.create_timer(0.1, self.discover)
            from std_srvs.srv import Trigger
            self.create_service(Trigger, '~/ready', self._srv_ready)

        def missing(self) -> list[str]:
            """
            Topics not yet recorded from every publisher the graph shows.

            A wanted topic not subscribed yet, or a subscription matched with fewer
            publishers than its topic has.
            """
            out = sorted(self.wanted - set(self.subs))
            for name, sub in sorted(self.subs.items()):
                if sub.get_publisher_count() < self.count_publishers(name):
                    out.append(f'{name} (not matched with every publisher yet)')
            return out

        def _srv_ready(self, request, response):
            left = self.missing()
            response.success = not left
            response.message = (f'recording {len(self.subs)} topics' if not left
                                else f'waiting for {", ".join(left)}')
            return response

        def discover(self) -> None:
            for name, types in self.get_topic_names_and_types():
                if name in self.subs or name in self.skipped:
                    continue
                if not (name in self.wanted or (self.all_topics and name not in EXCLUDED)):
                    continue
                if len(types) != 1:
                    self.skip(name, f'it has several types: {", ".join(types)}')
                    continue
                self.subscribe(name, types[0])

        def skip(self, name: str, why: str) -> None:
            self.skipped.add(name)
            print(f'record: not recording {name}: {why}', file=sys.stderr, flush=True)

        def subscribe(self, name: str, msgtype: str) -> None:
            infos = self.get_publishers_info_by_topic(name)
            if not infos:
                return  # known only from subscribers: wait for a publisher and its QoS
            if msgtype not in typestore().fielddefs:
                self.skip(name, f'type {msgtype} is not in the Jazzy typestore')
                return
            try:
                msg_cls = import_message(msgtype)
            except (ImportError, AttributeError, ValueError):
                self.skip(name, f'cannot import message type {msgtype}')
                return
            offered = [i.qos_profile for i in infos]
            conn = self.sink.add_connection(name, msgtype, [to_bag_qos(q) for q in offered])
            put = self.sink.put
            if self.sim_time:
                now = self.clock_.now

                def cb(data, info, conn=conn):
                    put(conn, now().nanoseconds, data)
            else:
                def cb(data, info, conn=conn):
                    put(conn, info['received_timestamp'] or time.time_ns(), data)
            self.subs[name] = self.create_subscription(
                msg_cls, name, cb, subscription_qos(offered, depth), raw=True)
            print(f'record: subscribed to {name} [{msgtype}]', flush=True)

    return Recorder()


def _interrupt(signum, frame):
    raise KeyboardInterrupt


def drain(executor, sink: BagSink, quiet: float = 3.5, limit: float = 8.0) -> None:
    """
    Take what is still on its way before closing the bag.

    A recorder sharing two cores with four busy nodes gets the small topics (camera_info,
    joint_states) of a fast lockstep run in late bursts, up to ~3 s behind their images
    (Fast DDS's reliable repair, at its 3 s heartbeat, of what the loaded localhost sockets
    dropped): stopping at once would lose the run's last seconds on them. Spins until no
    new message (repeats of a topic's previous one do not count) has arrived for ``quiet``
    s — longer than one heartbeat — and ``limit`` s at most (a live camera keeps sending;
    the launcher's SIGKILL comes after 10 s).
    """
    end = time.monotonic() + limit
    last, idle = sink.fresh, time.monotonic()
    while time.monotonic() < end and time.monotonic() - idle < quiet:
        executor.spin_once(timeout_sec=0.02)
        if sink.fresh != last:
            last, idle = sink.fresh, time.monotonic()


def main(args=None) -> int:
    import rclpy
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy.utilities import remove_ros_args
    from rosbags.rosbag2 import (CompressionFormat, CompressionMode, StoragePlugin, Writer,
                                 WriterError)

    argv = remove_ros_args(args=sys.argv if args is None else args)[1:]
    opts = parse_args(argv)
    out = opts.output or datetime.now().strftime('rosbag2_%Y_%m_%d-%H_%M_%S')
    try:
        path = check_new_output(out)
        writer = Writer(path, version=Writer.VERSION_LATEST,
                        storage_plugin=StoragePlugin[opts.storage.upper()])
        if opts.compression == 'zstd':
            mode = CompressionMode.STORAGE if opts.storage == 'mcap' else CompressionMode.MESSAGE
            writer.set_compression(mode, CompressionFormat.ZSTD)
        sink = BagSink(writer)
    except (BagError, WriterError, OSError) as err:
        print(f'record: error: {err}', file=sys.stderr)
        return 1
    topics = None if opts.all and opts.topics is None else (opts.topics or DEFAULT_TOPICS)

    # rclpy's own handler would shut the context down on Ctrl-C, and then nothing could be
    # drained: Ctrl-C and SIGTERM raise KeyboardInterrupt instead (as in ros/params.run)
    from rclpy.signals import SignalHandlerOptions
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    signal.signal(signal.SIGTERM, _interrupt)
    node = None
    started = time.monotonic()
    try:
        node = make_recorder(sink, topics, opts.all, opts.qos_depth)
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        print(f'record: recording to {path} ({opts.storage})', flush=True)
        deadline = None if opts.duration is None else time.monotonic() + opts.duration
        while rclpy.ok() and (deadline is None or time.monotonic() < deadline):
            executor.spin_once(timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        # a second Ctrl-C must not interrupt closing the bag
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        if node is not None:
            if rclpy.ok():
                try:
                    drain(executor, sink)
                except Exception as err:  # closing the bag matters more
                    print(f'record: warning: could not drain the queues: {err}',
                          file=sys.stderr)
            node.destroy_node()
        rclpy.try_shutdown()
        sink.close()
    elapsed = time.monotonic() - started
    total = sum(sink.counts.values())
    print(f'record: wrote {total} messages in {elapsed:.1f} s to {path}')
    for name, n in sorted(sink.counts.items()):
        print(f'  {name}: {n}')
    if sink.error is not None:
        print(f'record: error: writing failed: {sink.error}', file=sys.stderr)
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main())
