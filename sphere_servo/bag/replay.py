"""
replay: republish a rosbag2 (MCAP or sqlite3, ours or one by ``ros2 bag record``).

    ros2 run sphere_servo replay BAG [--topics T ...] [--rate R | --max-rate] [--loop]
                                 [--clock [HZ]] [--remap OLD:=NEW ...] [--delay S]
                                 [--wait-for-subscribers [S]]
                                 [--answer TOPIC:=ANSWER [--answer-timeout S]]

``BAG`` is a bag directory (with or without ``metadata.yaml``) or a bare ``.mcap`` /
``.db3`` file; every rosbag2 of Jazzy or older is read (:mod:`sphere_servo.bag.reader`:
topics matched by name as rosbag2 does, split bags, older metadata versions). Topics are
selected as stored or by their fully qualified name (``--topics AAA`` and ``--topics /AAA``
both select a topic stored as ``AAA``). Messages are republished as their serialized bytes
(never deserialized), with the bag's timing scaled by ``--rate``, on publishers with the QoS
the recording publishers offered (adapted as ``ros2 bag play`` does). A topic whose message
type is not installed is skipped with a warning naming it, as ``ros2 bag play`` does, and so
is a Jazzy type recorded with another definition (its type hash differs: subscribers would
misread its bytes), unless ``--topics`` asks for it: then replay stops with an error.
Before playing, replay says what it will play; a selection that plays nothing is an error
(exit 1). ``--clock`` publishes
``/clock`` from bag time (at HZ, default 40, and before each message), so nodes with
``use_sim_time`` follow the bag.

``--answer TOPIC:=ANSWER`` plays each message of TOPIC (after ``--remap``; or as a
``--ros-args -r`` rule renames it, which renames ANSWER too) only
once the previous one was answered: a message on ANSWER with the same header stamp (the
pipeline passes each image's header on), or ``--answer-timeout`` seconds (default 5)
passed. A node whose reader keeps only the newest frames (the detector: 5) then gets every
frame however loaded the machine is, as in the lockstep run that recorded them; bag timing
still applies (``--max-rate``: as fast as answered). Messages left unanswered are counted,
and make the exit code 1; three in a row, or the answer topic losing its publishers, stop
the replay. Interrupted, it exits 1 unless ``--loop``. (:mod:`sphere_servo.bag.answers`)
"""
from __future__ import annotations

import argparse
import math
import sys
import time

from sphere_servo.bag.answers import parse_answer, stamped
from sphere_servo.bag.bagio import (BagError, format_summary, iter_raw, open_bag, select,
                                    summary, topic_name)
from sphere_servo.bag.metadata import INFINITE


def parse_args(argv: list[str]) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog='replay', description=__doc__.strip().split('\n\n')[0])
    p.add_argument('bag', help='rosbag2 directory, or a bare .mcap / .db3 file')
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
    p.add_argument('--answer', action='append', metavar='TOPIC:=ANSWER',
                   help='after each message of TOPIC, wait for the message of ANSWER with '
                   'its header stamp')
    p.add_argument('--answer-timeout', type=float, default=None, metavar='S',
                   help='longest wait for an answer (default 5 s)')
    opts = p.parse_args(argv)
    if opts.answer is None and opts.answer_timeout is not None:
        p.error('--answer-timeout without --answer: there is nothing to wait for')
    if opts.answer_timeout is None:
        opts.answer_timeout = 5.0
    # one trigger: a second --answer would otherwise silently replace the first
    if opts.answer is not None and len(opts.answer) > 1:
        p.error(f'--answer given {len(opts.answer)} times; one TOPIC:=ANSWER is played')
    opts.answer = opts.answer and opts.answer[0]
    if not 0 < opts.answer_timeout < math.inf:
        p.error('--answer-timeout must be a finite number of seconds > 0, got '
                f'{opts.answer_timeout}')
    if not opts.max_rate and not opts.rate > 0:
        p.error('--rate must be > 0')
    if opts.clock is not None and not opts.clock > 0:
        p.error('--clock frequency must be > 0')
    # NaN compares false: each bound is written so that NaN fails it
    if not 0 <= opts.delay < math.inf:
        p.error(f'--delay must be a finite number of seconds >= 0, got {opts.delay}')
    if opts.wait_for_subscribers is not None and not 0 < opts.wait_for_subscribers < math.inf:
        p.error('--wait-for-subscribers must be a finite number of seconds > 0, got '
                f'{opts.wait_for_subscribers}')
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


def check_remaps(reader, conns, remaps: dict[str, str]) -> None:
    """
    Refuse remaps that would publish wrongly (raise BagError).

    A remap of a topic the bag does not have (a typo would play the topic under its own
    name), and two played topics of different types on one name (a publisher has one type:
    the bytes of one would go out as the other).
    """
    stored = {topic_name(c.topic) for c in reader.connections}
    unknown = sorted(set(remaps) - stored)
    if unknown:
        raise BagError(f'--remap of {", ".join(unknown)}: not in bag; it has: '
                       f'{", ".join(sorted(stored)) or "(no topics)"}')
    types: dict[str, tuple[str, str]] = {}
    for c in conns:
        name = topic_name(c.topic)
        target = remaps.get(name, name)
        first = types.setdefault(target, (c.msgtype, c.topic))
        if first[0] != c.msgtype:
            raise BagError(f'{c.topic} [{c.msgtype}] and {first[1]} [{first[0]}] would both '
                           f'be published on {target}: remap one of them elsewhere')


def _same_offer(a, b) -> bool:
    """Whether two offered profiles are the same where it matters for matching."""
    return (a.reliability, a.durability, a.deadline, a.liveliness,
            a.liveliness_lease_duration) == (b.reliability, b.durability, b.deadline,
                                             b.liveliness, b.liveliness_lease_duration)


def publisher_qos(conn):
    """
    Return the QoS to offer on a topic: the recorded publishers' one, keep-last ≥ 100.

    As rosbag2's ``adapt_offer_to_recorded_offers``: the first recorded profile when all
    offered the same (history and lifespan aside), else reliable / volatile. Finite
    deadline, lifespan and liveliness lease are offered again; infinite ones (however the
    bag spells them) stay the default.
    """
    from rclpy.duration import Duration
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    offered = getattr(conn.ext, 'offered_qos_profiles', None) or []
    qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                     reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.VOLATILE)
    if offered and all(_same_offer(o, offered[0]) for o in offered):
        o = offered[0]
        if o.reliability.name == 'BEST_EFFORT':
            qos.reliability = ReliabilityPolicy.BEST_EFFORT
        if o.durability.name == 'TRANSIENT_LOCAL':
            qos.durability = DurabilityPolicy.TRANSIENT_LOCAL
        qos.depth = max(100, o.depth)
        for key in ('deadline', 'lifespan', 'liveliness_lease_duration'):
            t = getattr(o, key)
            if t != INFINITE:
                setattr(qos, key, Duration(seconds=t.sec, nanoseconds=t.nsec))
    return qos


def unplayable(conn) -> str | None:
    """Return why a topic cannot be published here (its message type is not installed)."""
    from sphere_servo.bag.record import import_message
    try:
        import_message(conn.msgtype)
    except (ImportError, AttributeError, ValueError) as err:
        return f'its message type is not installed ({type(err).__name__}: {err})'
    return None


class Player:
    """Publishes ``(connection, t, raw)`` from a bag with scaled timing."""

    def __init__(self, node, reader, conns, opts, remaps):
        from rclpy.qos import QoSProfile
        from rosgraph_msgs.msg import Clock

        from sphere_servo.bag.record import import_message
        self.node, self.reader, self.conns, self.opts = node, reader, conns, opts
        self.remaps = remaps
        self.pubs = {}
        self.counts: dict[str, int] = {}
        for c in conns:
            name = remaps.get(topic_name(c.topic), c.topic)
            if name not in self.pubs:
                self.pubs[name] = node.create_publisher(import_message(c.msgtype), name,
                                                        publisher_qos(c))
                self.counts[name] = 0
        self.topic_of = {c.id: remaps.get(topic_name(c.topic), c.topic) for c in conns}
        self.Clock = Clock
        self.clock_pub = node.create_publisher(Clock, '/clock', QoSProfile(depth=10)) \
            if opts.clock else None
        self.clock_period = 1.0 / opts.clock if opts.clock else None
        self.answers = self.answer_key = None  # with --answer: check_, start_answers

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
            trigger = self.answers is not None and topic == self.answer_key
            if trigger:
                self.answers.ask(raw)
            self.pubs[topic].publish(raw)
            self.counts[topic] += 1
            sent += 1
            if trigger:
                self.answers.wait()
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

    def check_answers(self, trigger: str, answer: str) -> None:
        """
        Note the publisher key of ``trigger``; BagError if --answer cannot work.

        ``trigger`` is a topic as played (after ``--remap``) or as ``--ros-args -r`` rules
        rename it; ``answer`` is compared as those rules rename it.
        """
        keys = {topic_name(k): k for k in self.pubs}
        # where each publisher and the answer's subscription really are (rcl's remap rules)
        resolved = {self.node.resolve_topic_name(k): k for k in self.pubs}
        keys.update({r: k for r, k in resolved.items() if r not in keys})
        if trigger not in keys:
            moved = self.remaps.get(trigger)
            raise BagError(f'--answer: {trigger} is not played'
                           + (f' (--remap publishes it on {moved})' if moved else '')
                           + f'; the topics played are {", ".join(sorted(keys))}')
        if answer in keys or self.node.resolve_topic_name(answer) in resolved:
            # its recorded messages would pass for answers, and replay for its publisher
            raise BagError(f'--answer: {answer} is played from the bag too; leave it out '
                           '(--topics) or --remap it to answer on it')
        if not stamped(self.pubs[keys[trigger]].msg_type):
            raise BagError(f'--answer: {trigger} carries no header to match answers by')
        if not sum(c.msgcount for c in self.conns if self.topic_of[c.id] == keys[trigger]):
            # before the wait for subscribers: the other topics' may never come
            raise BagError(f'--answer: the bag holds no message of {trigger}: nothing would '
                           'be waited for')
        self.answer_key = keys[trigger]

    def start_answers(self, trigger: str, answer: str, timeout: float) -> None:
        """Wait for answers on ``answer`` to ``trigger`` (checked by :meth:`check_answers`)."""
        from sphere_servo.bag.answers import Answers
        self.answers = Answers(self.node, trigger, answer, timeout)

    def wait_for_subscribers(self, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if all(p.get_subscription_count() > 0 for p in self.pubs.values()):
                return True
            time.sleep(0.05)
        return False


def report_answers(answers, loop: bool, interrupted: bool) -> int:
    """Say how the answers went; return the exit code they call for."""
    a = answers
    if interrupted:
        pending = '' if a.waiting is None else \
            f' while waiting for the answer to the message stamped {a.waiting}'
        print(f'replay: interrupted{pending}: {a.asked - a.unanswered} of {a.asked} messages '
              f'of {a.trigger} before it answered', file=sys.stderr)
    err = a.report()
    if not err and not interrupted and not a.asked:
        err = f'no message of {a.trigger} was played: nothing was waited for'
    if err:
        print(f'replay: error: {err}', file=sys.stderr)
        return 1
    # cut short, the bag was not played answered; with --loop a signal is the way to end
    return 1 if interrupted and not loop else 0


def main(args=None) -> int:
    import rclpy
    from rclpy.executors import ExternalShutdownException
    full = list(sys.argv if args is None else args)
    ours, ros_args = split_ros_args(full[1:])
    opts = parse_args(ours)
    try:
        remaps = parse_remaps(opts.remap)
        answer = None if opts.answer is None else parse_answer(opts.answer)
        reader = open_bag(opts.bag)
    except BagError as err:
        print(f'replay: error: {err}', file=sys.stderr)
        return 1
    try:
        sel = select(reader, opts.topics, unplayable)
        info = summary(reader, opts.topics, unplayable)
        check_remaps(reader, sel.connections, remaps)
        if not sel.count:
            raise BagError(f'nothing to play: the selection ({len(sel.connections)} topics, '
                           f'{len(sel.skipped)} skipped) holds no message')
    except BagError as err:
        reader.close()
        print(f'replay: error: {err}', file=sys.stderr)
        return 1
    for w in reader.warnings:
        print(f'replay: warning: {w}', file=sys.stderr, flush=True)
    for s in sel.skipped:
        print(f'replay: warning: skipping {s.topic} [{s.msgtype}], {s.count} messages: '
              f'{s.reason}', file=sys.stderr, flush=True)

    rclpy.init(args=full[:1] + ros_args)
    node = None
    player = None
    code = 0
    interrupted = False
    started = time.monotonic()
    try:
        node = rclpy.create_node('replay')
        player = Player(node, reader, sel.connections, opts, remaps)
        if answer is not None:   # before waiting for subscribers: a wrong --answer fails fast
            player.check_answers(*answer)
        if opts.wait_for_subscribers is not None and \
                not player.wait_for_subscribers(opts.wait_for_subscribers):
            print('replay: warning: not every topic has a subscriber; playing anyway',
                  file=sys.stderr, flush=True)
        if answer is not None:
            player.start_answers(*answer, opts.answer_timeout)
        if opts.delay > 0:
            time.sleep(opts.delay)
        print(f'replay: playing {opts.bag}: {sel.count} messages on {len(sel.connections)} '
              f'topics\n{format_summary(info)}', flush=True)
        started = time.monotonic()
        while True:
            sent = player.play_once()
            if not opts.loop or not rclpy.ok() or sent == 0:
                break
        interrupted = not rclpy.ok()   # SIGTERM shut the context down
        player.flush()
    except (KeyboardInterrupt, ExternalShutdownException):
        interrupted = True
    except BagError as err:
        print(f'replay: error: {err}', file=sys.stderr)
        code = 1
    except Exception as err:  # e.g. publishing after an external shutdown
        if rclpy.ok():
            print(f'replay: error: {type(err).__name__}: {" ".join(str(err).split())}',
                  file=sys.stderr)
            code = 1
        else:
            interrupted = True
    finally:
        reader.close()
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    if player is not None and player.answers is not None:
        code = max(code, report_answers(player.answers, opts.loop, interrupted))
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
