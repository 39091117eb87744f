"""
``replay --answer TOPIC:=ANSWER``: play a message of TOPIC only once the last one was answered.

A pipeline node whose reader keeps only the newest frames (the detector keeps 5) skips
frames when replay publishes faster than it answers, on a loaded machine at the lockstep
run's pace. :class:`Answers` makes the replay wait, after each message of TOPIC, for the
message on ANSWER that carries the same header stamp (every node of the pipeline passes the
image's header on), at most a timeout. Stamps are read from the serialized bytes
(:func:`header_stamp`): replay never deserializes what it plays.
"""
from __future__ import annotations

from collections import Counter
import struct
import sys
import time

from sphere_servo.bag.bagio import BagError, topic_name

# CDR encapsulation identifiers (first two bytes, big-endian) → byte order of the payload:
# CDR and XCDR2 plain, big and little endian
_ORDER = {0x0000: '>', 0x0001: '<', 0x0006: '>', 0x0007: '<'}


def header_stamp(raw: bytes) -> int | None:
    """
    Return the header stamp (ns) of a serialized message that starts with a Header, or None.

    A ``std_msgs/Header`` first field puts ``stamp.sec`` (int32) and ``stamp.nanosec``
    (uint32) right after the 4-byte encapsulation; None for bytes too short, an
    encapsulation that is not plain CDR, or a nanosec ≥ 1e9 (not a stamp).
    """
    if len(raw) < 12:
        return None
    order = _ORDER.get(int.from_bytes(bytes(raw[:2]), 'big'))
    if order is None:
        return None
    sec, nsec = struct.unpack_from(order + 'iI', raw, 4)
    return sec * 1_000_000_000 + nsec if nsec < 1_000_000_000 else None


def parse_answer(text: str) -> tuple[str, str]:
    """Return (TOPIC, ANSWER) of ``TOPIC:=ANSWER``, fully qualified; BagError if malformed."""
    trigger, sep, answer = text.partition(':=')
    if not sep or not trigger.strip() or not answer.strip():
        raise BagError(f'bad --answer {text!r}: expected TOPIC:=ANSWER')
    trigger, answer = topic_name(trigger.strip()), topic_name(answer.strip())
    if trigger == answer:
        raise BagError(f'--answer {text!r}: a topic cannot answer itself')
    return trigger, answer


def _stamped(cls) -> bool:
    """Tell whether the message class ``cls`` has a std_msgs/Header as its first field."""
    fields = list(cls.get_fields_and_field_types().values())
    return bool(fields) and fields[0] == 'std_msgs/Header'


class Answers:
    """
    The answers to the messages of ``trigger`` on ``answer`` (see the module docstring).

    ``trigger_type``: the message class played on ``trigger``. Raises BagError when either
    type has no header first, or when ``answer`` has no publisher within ``timeout`` s.
    """

    def __init__(self, node, trigger: str, trigger_type, answer: str, timeout: float):
        from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile,
                               ReliabilityPolicy)

        from sphere_servo.bag.record import import_message
        if not _stamped(trigger_type):
            raise BagError(f'--answer: {trigger} carries no header to match answers by')
        self.node, self.trigger, self.answer, self.timeout = node, trigger, answer, timeout
        deadline = time.monotonic() + timeout
        types = []
        while not types and time.monotonic() < deadline:
            types = dict(node.get_topic_names_and_types()).get(answer, [])
            if not types:
                time.sleep(0.05)
        if not types:
            raise BagError(f'--answer: nothing publishes {answer} (waited {timeout:g} s)')
        cls = import_message(types[0])
        if not _stamped(cls):
            raise BagError(f'--answer: {answer} [{types[0]}] carries no header')
        # best effort matches every writer; reliable only reliable ones
        best_effort = any(i.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT
                          for i in node.get_publishers_info_by_topic(answer))
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000,
                         durability=DurabilityPolicy.VOLATILE,
                         reliability=ReliabilityPolicy.BEST_EFFORT if best_effort
                         else ReliabilityPolicy.RELIABLE)
        self.seen: Counter = Counter()   # stamp → answers not yet waited for
        sub = node.create_subscription(cls, answer, self._on_answer, qos, raw=True)
        # matched before the first message is played: its answer is not lost
        while sub.get_publisher_count() == 0 and time.monotonic() < deadline:
            time.sleep(0.02)
        self.asked = self.unanswered = 0

    def _on_answer(self, raw: bytes) -> None:
        stamp = header_stamp(raw)
        if stamp is not None:
            self.seen[stamp] += 1

    def wait(self, raw: bytes) -> bool:
        """Wait for the answer to the message ``raw`` just played; tell whether it came."""
        import rclpy
        self.asked += 1
        stamp = header_stamp(raw)
        deadline = time.monotonic() + self.timeout
        while self.seen[stamp] == 0 and rclpy.ok():
            left = deadline - time.monotonic()
            if left <= 0:
                break
            rclpy.spin_once(self.node, timeout_sec=min(left, 0.05))
        if self.seen[stamp] > 0:
            self.seen[stamp] -= 1
            return True
        self.unanswered += 1
        if self.unanswered <= 3:
            print(f'replay: warning: no answer on {self.answer} to the {self.trigger} message '
                  f'stamped {stamp} in {self.timeout:g} s', file=sys.stderr, flush=True)
        return False
