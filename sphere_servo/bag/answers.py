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
    from rclpy.exceptions import InvalidTopicNameException
    from rclpy.validate_full_topic_name import validate_full_topic_name
    trigger, sep, answer = text.partition(':=')
    if not sep or not trigger.strip() or not answer.strip():
        raise BagError(f'bad --answer {text!r}: expected TOPIC:=ANSWER')
    trigger, answer = topic_name(trigger.strip()), topic_name(answer.strip())
    for name in (trigger, answer):
        # '/a:=/b:=/c' or '/a b' would otherwise be waited for as a topic nobody publishes
        try:
            validate_full_topic_name(name)
        except InvalidTopicNameException as err:
            why = str(err).splitlines()[0].split('topic name ', 1)[-1].rstrip(':')
            raise BagError(f'bad --answer {text!r}: {name!r}: {why}') from None
    if trigger == answer:
        raise BagError(f'--answer {text!r}: a topic cannot answer itself')
    return trigger, answer


def stamped(cls) -> bool:
    """Tell whether the message class ``cls`` has a std_msgs/Header as its first field."""
    fields = list(cls.get_fields_and_field_types().values())
    return bool(fields) and fields[0] == 'std_msgs/Header'


class Answers:
    """
    The answers to the messages of ``trigger`` on ``answer`` (see the module docstring).

    Raises BagError when ``answer``'s type has no header first (``trigger``'s is checked by
    replay before), or when ``answer`` has no publisher within ``timeout`` s.
    Only an answer received after its message was published counts: the stamps repeat
    (``--loop``, a bag with repeated or zero stamps), and a second publisher's answer, or one
    that came too late, would otherwise answer the next message of that stamp at once.
    """

    def __init__(self, node, trigger: str, answer: str, timeout: float):
        from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile,
                               ReliabilityPolicy)

        from sphere_servo.bag.record import import_message
        self.node, self.trigger, self.timeout = node, trigger, timeout
        # the topic the subscription is on: --ros-args -r rules rename it as they do any
        where = node.resolve_topic_name(answer)
        self.answer = answer if where == answer else f'{answer} (remapped to {where})'
        deadline = time.monotonic() + timeout
        types = []
        while not types and time.monotonic() < deadline:
            types = dict(node.get_topic_names_and_types()).get(where, [])
            if not types:
                time.sleep(0.05)
        if not types:
            raise BagError(f'--answer: nothing publishes {self.answer} (waited {timeout:g} s)')
        if len(types) > 1:
            # a subscription has one type: the other type's answers would never arrive
            raise BagError(f'--answer: {self.answer} is published with several types: '
                           f'{", ".join(types)}')
        cls = import_message(types[0])
        if not stamped(cls):
            raise BagError(f'--answer: {self.answer} [{types[0]}] carries no header')
        # best effort matches every writer; reliable only reliable ones
        best_effort = any(i.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT
                          for i in node.get_publishers_info_by_topic(where))
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000,
                         durability=DurabilityPolicy.VOLATILE,
                         reliability=ReliabilityPolicy.BEST_EFFORT if best_effort
                         else ReliabilityPolicy.RELIABLE)
        self.stamp = self.since = None   # the message waited for, and when it was published
        self.got = 0                     # its answers received since
        self.early = 0                   # answers received before their message was published
        self.others, self.other = 0, None   # answers to no message waited for: count, last
        self.sub = node.create_subscription(cls, answer, self._on_answer, qos, raw=True)
        # matched before the first message is played: its answer is not lost
        while self.sub.get_publisher_count() == 0 and time.monotonic() < deadline:
            time.sleep(0.02)
        self.asked = self.unanswered = self.streak = 0
        self.waiting = None   # the stamp of a wait cut short by a signal

    def _on_answer(self, raw: bytes, info) -> None:
        stamp = header_stamp(raw)
        if self.since is None or info.get('received_timestamp', self.since) < self.since:
            self.early += 1
        elif stamp == self.stamp:
            self.got += 1
        else:
            self.others, self.other = self.others + 1, stamp

    def ask(self, raw: bytes) -> None:
        """Take note that ``raw`` is being published now: answers from here on count."""
        stamp = header_stamp(raw)
        if stamp is None:
            raise BagError(f'--answer: a message of {self.trigger} has no header stamp '
                           f'replay can read (encapsulation {bytes(raw[:2]).hex()}, '
                           f'{len(raw)} bytes): answers cannot be matched to it')
        self.stamp, self.since, self.got = stamp, time.time_ns(), 0

    def wait(self) -> bool:
        """
        Wait for the answer to the message of :meth:`ask`; tell whether it came.

        Raises BagError when answers stopped (:data:`STREAK` messages in a row unanswered,
        or the answer topic lost its last publisher): the rest would wait in vain.
        """
        import rclpy
        deadline = time.monotonic() + self.timeout
        self.waiting = self.stamp
        while self.got == 0 and rclpy.ok():
            left = deadline - time.monotonic()
            if left <= 0 or self.sub.get_publisher_count() == 0:
                break
            rclpy.spin_once(self.node, timeout_sec=min(left, 0.05))
        if not rclpy.ok():   # a signal: the wait was cut short, not unanswered
            return False
        self.waiting = None
        self.asked += 1
        if self.got:
            self.streak = 0
            return True
        self.unanswered += 1
        self.streak += 1
        if self.unanswered <= 3:
            print(f'replay: warning: no answer on {self.answer} to the {self.trigger} message '
                  f'stamped {self.stamp} in {self.timeout:g} s', file=sys.stderr, flush=True)
        gone = self.sub.get_publisher_count() == 0
        if gone or self.streak >= STREAK:
            why = f'nothing publishes {self.answer} any more' if gone else \
                f'the last {self.streak} messages of {self.trigger} had no answer'
            raise BagError(f'stopped: {why}')
        return False

    def hint(self) -> str:
        """Say what came on the answer topic instead, if anything."""
        text = ''
        if self.others:
            text += (f'; {self.others} answers on {self.answer} carried other stamps '
                     f'(the last {self.other}): does the answering node restamp?')
        if self.early:
            text += f'; {self.early} came before their message was played (not counted)'
        return text

    def report(self) -> str | None:
        """Return the error to print when messages went unanswered, else None."""
        if not self.unanswered:
            return None
        return (f'{self.unanswered} of {self.asked} messages of {self.trigger} had no '
                f'answer on {self.answer} within {self.timeout:g} s{self.hint()}')


# consecutive unanswered messages that stop the replay: a pipeline that dropped one frame
# answers the next; three in a row mean it stopped answering (killed, restamping, not
# subscribed), and waiting the timeout for every remaining message would look like a hang
STREAK = 3
