"""
record: write live topics into a rosbag2 (MCAP or sqlite3), as ``ros2 bag record`` does.

    ros2 run sphere_servo record [-o OUT] [--storage mcap|sqlite3] [--compression zstd]
                                 [--topics T ...] [--all] [--duration S] [--qos-depth N]

Topics are subscribed raw (serialized CDR, never deserialized) as soon as they appear in the
graph with a publisher, with the QoS rosbag2 adapts to the publishers; each message is
stamped with its receive time (the node clock when ``use_sim_time`` is set), its sender's
stamp kept as MCAP ``publish_time``, and written by a writer thread
(:class:`~sphere_servo.bag.writer.BagWriter`, Jazzy's layout and metadata), so the executor
only queues bytes. The service ``/recorder/ready`` (std_srvs/Trigger) answers success once
every topic asked for is subscribed and matched with each of its publishers (the launcher
waits for it before the run begins: under load, discovering a node's topics can take
seconds); otherwise its message names what is still missing. ``/recorder/idle`` answers
success once nothing new (a copy of a topic's last message and the 1 Hz ``/diagnostics``
are not) has arrived for ``--idle-quiet`` s (3.5 by default, longer than Fast DDS's 3 s
heartbeat: a supervisor that stops a run can wait for it, so that what the loaded
middleware delivers late is in the bag before it interrupts the recorder).

Losing little: the writer commits at the latest 0.5 s after a message was written (MCAP:
the open chunk written out and fsynced; sqlite3: the transaction committed, WAL fsynced), so
SIGKILL or a power loss loses at most the last 0.5 s; ``reindex BAG`` then rebuilds a complete
bag (:mod:`sphere_servo.bag.repair`). Ctrl-C, SIGTERM or the end of ``--duration`` stop it
at once: the time of the interrupt is the cut; what the recorder had already taken in, and
what its subscriptions already hold that was sent or received before the cut, goes in the
bag; anything later does not; the subscriptions are then destroyed and the bag closed,
within a second. A recording that wrote no message did nothing: it exits 1, naming the
topics it had subscribed to (the empty bag is left as it is).
"""
from __future__ import annotations

import argparse
from datetime import datetime
import importlib
import math
import os
import queue
import signal
import sys
import threading
import time

from sphere_servo.bag.bagio import BagError, check_new_output, qos_time, topic_name, typestore
from sphere_servo.bag.writer import BagWriter

# the pipeline's topics (module docstrings of ros/arm_sim, detector, features, servo):
# enough to regenerate the features offline (``refeatures``) and to compare with what ran;
# arm_sim/markers so that Foxglove shows the 3-D scene when the bag is opened
DEFAULT_TOPICS = ['camera/image_raw', 'camera/camera_info', 'detector/measurement',
                  'features/s_n', 'features/s_n/desired', 'camera/cmd_vel', 'servo/state',
                  'ground_truth/camera_pose', 'joint_states', 'arm_sim/state', '/diagnostics',
                  'arm_sim/markers']
# never recorded by --all (as ros2 bag record --all)
EXCLUDED = {'/rosout', '/parameter_events'}
# published at 1 Hz whatever happens: recorded, but never "something new" for ~/idle
HEARTBEATS = {'/diagnostics'}
DRAIN_IDLE = 0.2    # s: the drain ends when the subscriptions stay empty this long
DRAIN_LIMIT = 0.5   # s: and at the latest after this
_CUT = {'ns': None}  # wall time of the interrupt (set by the signal handler)


def parse_args(argv: list[str]) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog='record', description=__doc__.strip().split('\n\n')[0])
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
    p.add_argument('--commit-period', type=float, default=0.5,
                   help='s: the most a crash or a power loss can lose (default 0.5)')
    p.add_argument('--idle-quiet', type=float, default=3.5,
                   help='s without anything new before ~/idle reports success (default 3.5)')
    opts = p.parse_args(argv)
    if not opts.commit_period > 0:
        p.error('--commit-period must be > 0')
    # NaN compares false: each bound is written so that NaN fails it
    if opts.duration is not None and not 0 < opts.duration < math.inf:
        p.error(f'--duration must be a finite number of seconds > 0, got {opts.duration}')
    if not opts.qos_depth >= 1:
        p.error(f'--qos-depth must be >= 1, got {opts.qos_depth}')
    if not 0 <= opts.idle_quiet < math.inf:
        p.error(f'--idle-quiet must be a finite number of seconds >= 0, got {opts.idle_quiet}')
    from rclpy.exceptions import InvalidTopicNameException
    from rclpy.validate_full_topic_name import validate_full_topic_name
    for t in opts.topics or []:
        try:  # a name no publisher can have would be waited for in vain
            validate_full_topic_name(topic_name(t))
        except InvalidTopicNameException:
            p.error(f'--topics: {t!r} is not a valid topic name')
    return opts


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
    """A topic's entry in the bag, bound by the writer thread."""

    __slots__ = ('name', 'entry')

    def __init__(self, name: str):
        self.name, self.entry = name, None


class BagSink:
    """
    A :class:`BagWriter` owned by one thread (sqlite3 objects stay in the thread that made them).

    The thread opens the bag, adds topics and writes messages from a FIFO queue, committing
    at the writer's commit period, so the executor only queues bytes; ``close()`` writes
    what is queued and closes the bag.
    """

    def __init__(self, writer: BagWriter):
        self.writer = writer
        self.queue: queue.SimpleQueue = queue.SimpleQueue()
        self.counts: dict[str, int] = {}
        self.received = 0  # messages queued so far (the executor's side)
        self.fresh = 0     # of those, not a byte-identical repeat of the topic's previous one
        self.last_fresh = time.monotonic()
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

    def put(self, handle: _Topic, stamp_ns: int, data: bytes, sent_ns: int = 0) -> None:
        self.received += 1
        # not new: a copy (an idle lockstep arm_sim re-publishes) or a heartbeat
        if handle.name not in HEARTBEATS and self._prev.get(handle.name) != data:
            self.fresh += 1
            self.last_fresh = time.monotonic()
            self._prev[handle.name] = data
        self.queue.put((handle, stamp_ns, data, sent_ns or stamp_ns))

    def _run(self) -> None:
        w = self.writer
        try:
            w.create()
        except BaseException as err:
            self.error = err
            self._opened.set()
            return
        self._opened.set()
        while True:
            try:
                item = self.queue.get(timeout=w.seconds_to_commit())
            except queue.Empty:
                item = ()
            try:
                if item is None:
                    break
                if item and item[0] == 'add':
                    _, handle, msgtype, offered = item
                    handle.entry = w.add_topic(handle.name, msgtype, offered,
                                               typestore=typestore())
                elif item:
                    handle, stamp, data, sent = item
                    if handle.entry is not None:
                        w.write(handle.entry, stamp, data, sent)
                        self.counts[handle.name] += 1
                if w.commit_due():
                    w.commit()
            except Exception as err:  # keep draining; reported at exit
                self.error = err
        try:
            w.close()
        except Exception as err:
            self.error = err
            w.abort()

    def close(self) -> None:
        self.queue.put(None)
        self.thread.join()


def _take(sub):
    """Take one message waiting in a subscription's queue: (bytes, info) or None."""
    with sub.handle:
        return sub.handle.take_message(sub.msg_type, sub.raw)


def make_recorder(sink: BagSink, topics: list[str] | None, all_topics: bool, depth: int,
                  idle_quiet: float = 3.5):
    from rclpy.node import Node

    class Recorder(Node):

        def __init__(self):
            super().__init__('recorder')
            self.sink = sink
            self.wanted = {topic_name(t) for t in (topics or [])}
            self.all_topics = all_topics
            self.subs: dict[str, object] = {}
            self.callbacks: dict[str, object] = {}
            self.skipped: set[str] = set()
            self.late = 0  # messages the drain found that came after the cut
            self.sim_time = self.get_parameter('use_sim_time').value
            self.clock_ = self.get_clock()
            self.discover()
            missing = sorted(self.wanted - set(self.subs))
            if missing:
                print(f'record: waiting for {", ".join(missing)}', flush=True)
            self.timer = self.create_timer(0.1, self.discover)
            from std_srvs.srv import Trigger
            self.create_service(Trigger, '~/ready', self._srv_ready)
            self.create_service(Trigger, '~/idle', self._srv_idle)
            self.idle_quiet = idle_quiet

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

        def _srv_idle(self, request, response):
            quiet = time.monotonic() - self.sink.last_fresh
            response.success = quiet >= self.idle_quiet
            response.message = f'nothing new for {quiet:.1f} s; {self.sink.received} received'
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
                    put(conn, now().nanoseconds, data, info.get('source_timestamp', 0))
            else:
                def cb(data, info, conn=conn):
                    put(conn, info.get('received_timestamp') or time.time_ns(), data,
                        info.get('source_timestamp', 0))
            self.callbacks[name] = cb
            self.subs[name] = self.create_subscription(
                msg_cls, name, cb, subscription_qos(offered, depth), raw=True)
            print(f'record: subscribed to {name} [{msgtype}]', flush=True)

        def stop(self, cut_ns: int) -> int:
            """
            Stop recording at wall time ``cut_ns``; return how many messages were drained.

            Takes what the subscriptions already hold that was sent or received before the
            cut (a subscription is done at its first later message, all of them once none
            has had anything for DRAIN_IDLE s, DRAIN_LIMIT s at most), then destroys them.
            """
            self.destroy_timer(self.timer)
            left = dict(self.subs)
            taken = 0
            end = time.monotonic() + DRAIN_LIMIT
            idle_since = time.monotonic()
            while left and time.monotonic() < end:
                got = False
                for name, sub in list(left.items()):
                    while True:
                        item = _take(sub)
                        if item is None:
                            break
                        data, info = item
                        stamps = [t for t in (info.get('received_timestamp'),
                                              info.get('source_timestamp')) if t]
                        if stamps and min(stamps) > cut_ns:
                            self.late += 1
                            del left[name]
                            break
                        self.callbacks[name](data, info)
                        taken += 1
                        got = True
                if got:
                    idle_since = time.monotonic()
                elif time.monotonic() - idle_since >= DRAIN_IDLE:
                    break
                else:
                    time.sleep(0.002)
            for sub in self.subs.values():
                self.destroy_subscription(sub)
            self.subs.clear()
            return taken

    return Recorder()


def _interrupt(signum, frame):
    """Note the cut; the spin loop ends at its next turn (callbacks are never cut short)."""
    if _CUT['ns'] is None:
        _CUT['ns'] = time.time_ns()


def _watch_signals() -> None:
    """
    Note the time of a signal as it is delivered.

    Python runs ``_interrupt`` only once the main thread is back from rclpy's wait, up to a
    spin timeout later; the wake-up fd is written at delivery, and this thread reads it.
    """
    r, w = os.pipe()
    os.set_blocking(w, False)
    signal.set_wakeup_fd(w)

    def run():
        while os.read(r, 64):
            if _CUT['ns'] is None:
                _CUT['ns'] = time.time_ns()
    threading.Thread(target=run, name='signal-watch', daemon=True).start()


def main(args=None) -> int:
    import rclpy
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy.utilities import remove_ros_args

    argv = remove_ros_args(args=sys.argv if args is None else args)[1:]
    opts = parse_args(argv)
    out = opts.output or datetime.now().strftime('rosbag2_%Y_%m_%d-%H_%M_%S')
    try:
        path = check_new_output(out)
        sink = BagSink(BagWriter(path, opts.storage, opts.compression,
                                 commit_period=opts.commit_period))
    except (BagError, OSError) as err:
        print(f'record: error: {err}', file=sys.stderr)
        return 1
    topics = None if opts.all and opts.topics is None else (opts.topics or DEFAULT_TOPICS)

    # rclpy's own handler would shut the context down on Ctrl-C, and then the subscriptions'
    # queues could not be drained: Ctrl-C and SIGTERM note the time of the cut instead
    from rclpy.signals import SignalHandlerOptions
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    signal.signal(signal.SIGINT, _interrupt)
    signal.signal(signal.SIGTERM, _interrupt)
    _watch_signals()
    node = None
    started = time.monotonic()
    drained = 0
    try:
        node = make_recorder(sink, topics, opts.all, opts.qos_depth, opts.idle_quiet)
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        print(f'record: recording to {path} ({opts.storage})', flush=True)
        deadline = None if opts.duration is None else time.monotonic() + opts.duration
        while rclpy.ok() and _CUT['ns'] is None and \
                (deadline is None or time.monotonic() < deadline):
            executor.spin_once(timeout_sec=0.05)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        cut = _CUT['ns'] or time.time_ns()
        stopping = time.monotonic()
        if node is not None:
            if rclpy.ok():
                try:
                    drained = node.stop(cut)
                except Exception as err:  # closing the bag matters more
                    print(f'record: warning: could not drain the queues: {err}',
                          file=sys.stderr)
            node.destroy_node()
        rclpy.try_shutdown()
        sink.close()
    total = sum(sink.counts.values())
    print(f'record: wrote {total} messages in {time.monotonic() - started:.1f} s to {path}'
          f' (stopped in {time.monotonic() - stopping:.2f} s: {drained} messages taken from '
          f'the queues, {node.late if node else 0} later than the interrupt left out)')
    for name, n in sorted(sink.counts.items()):
        print(f'  {name}: {n}')
    if sink.error is not None:
        print(f'record: error: writing failed: {sink.error}', file=sys.stderr)
        return 1
    if total == 0:  # a bag with nothing in it: the tool did nothing, say why
        subscribed = sorted(node.callbacks) if node is not None else []
        print('record: error: no message was recorded '
              + (f'(subscribed to {", ".join(subscribed)}, none published)' if subscribed
                 else '(no topic asked for had a publisher)') + f'; the bag {path} is empty',
              file=sys.stderr)
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main())
