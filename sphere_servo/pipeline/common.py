"""
What the node cores share (no ROS): diagnostic levels, node statuses, stamps, refusals.

Stamps are int nanoseconds (``sec · 10⁹ + nanosec`` of a ROS header); :func:`stamp_text`
writes one as ROS tools print a time, ``SEC.NANOSEC`` with nine digits. A stamp of 0 means
"no image" (a message that answers none), as many ROS tools read a zero stamp as unset.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum, IntEnum

NS = 1_000_000_000
#: the first stamp a header cannot carry: ``builtin_interfaces/Time.sec`` is an int32, and
#: rclpy serializes a larger one wrapped (2^40 + 5 s goes out as 5 s), without an error
STAMP_END_NS = 2**31 * NS


class Level(IntEnum):
    """Severity of a status (the values of ``diagnostic_msgs/DiagnosticStatus.level``)."""

    OK = 0
    WARN = 1
    ERROR = 2


@dataclass(frozen=True)
class NodeStatus:
    """
    A node's status: its state, how serious it is, and named values (key → text).

    ``state`` is one of the node's state enums (``ServoState``, ``DetectStatus``, ``Status``,
    ``FeaturesState``), whose value is the published status message; the ros layer puts it
    on the node's ``~/state`` and on ``/diagnostics`` (``diagnostic_msgs/DiagnosticStatus``:
    level, message, values).
    """

    state: Enum
    level: Level
    values: dict[str, str] = field(default_factory=dict)

    @property
    def message(self) -> str:
        """Return the status message: the state's value."""
        return self.state.value


@dataclass(frozen=True)
class Reply:
    """The answer of a request (a ``std_srvs/Trigger`` service): success and the message."""

    success: bool
    message: str


@dataclass(frozen=True)
class Refusal:
    """An input a core refused, and why (the output it stands for is not produced)."""

    reason: str


def stamp_ns(sec: int, nanosec: int) -> int:
    """Nanoseconds of a header stamp."""
    return int(sec) * NS + int(nanosec)


def stamp_text(ns: int) -> str:
    """``SEC.NANOSEC`` (nine digits) of a stamp in nanoseconds, e.g. ``1.033333333``."""
    return f'{ns // NS}.{ns % NS:09d}'


def parse_stamp(text: str) -> int:
    """Nanoseconds of ``SEC`` or ``SEC.FRACTION`` (up to nine digits kept); ValueError."""
    sec, _, frac = text.strip().partition('.')
    return int(sec) * NS + int((frac + '0' * 9)[:9] or 0)
