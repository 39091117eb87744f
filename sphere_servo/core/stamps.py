"""
The rule for message stamps from outside: not in the future, monotonic per source (no ROS).

Stamps are int nanoseconds (``sec · 10⁹ + nanosec`` of a header); ``now_ns`` is the
receiver's clock (sim time under ``use_sim_time``). :meth:`StampRule.check` gives one
:class:`StampVerdict` per stamp, tested in this order:

- ``REPEAT``     the stamp equals the last one accepted from the same source (a
  re-publication of the same image: answered once);
- ``BACKWARDS``  it is older than the last accepted one from that source (a source's
  stamps only grow; a replayed or restarted source calls :meth:`StampRule.forget`);
- ``FUTURE``     it is later than ``now_ns + future_tolerance_ns``. The tolerance covers
  clocks that are equal only up to delivery: under sim time the clock and the images come
  on different topics, so a receiver may see an image before the ``/clock`` of its stamp;
  give it at least one frame period;
- ``TOO_OLD``    (only with ``max_age_ns``) ``now_ns − stamp > max_age_ns``;
- ``ACCEPTED``   otherwise; only an accepted stamp becomes the source's last one, so a
  refused stamp never blocks the ones after it.
"""
from __future__ import annotations

from collections.abc import Hashable
from dataclasses import dataclass, field
from enum import Enum


class StampVerdict(str, Enum):
    """What became of a stamp (the value is the text a log line can use)."""

    ACCEPTED = 'accepted'
    REPEAT = 'repeat of the last stamp'
    BACKWARDS = 'older than the last stamp of its source'
    FUTURE = 'in the future'
    TOO_OLD = 'too old'


@dataclass(frozen=True)
class StampCheck:
    """
    The verdict on one stamp, with the numbers behind it (ns).

    ``reference_ns`` is what the stamp was compared with: the source's last accepted stamp
    (REPEAT, BACKWARDS) or ``now_ns`` (the others); ``delta_ns = stamp_ns − reference_ns``.
    """

    verdict: StampVerdict
    source: Hashable
    stamp_ns: int
    reference_ns: int
    delta_ns: int

    @property
    def accepted(self) -> bool:
        return self.verdict is StampVerdict.ACCEPTED

    def __str__(self) -> str:
        return (f'stamp {self.stamp_ns} ns from {self.source!r}: {self.verdict.value} '
                f'({self.delta_ns * 1e-9:+.9f} s from {self.reference_ns} ns)')


@dataclass
class StampRule:
    """
    Not in the future beyond ``future_tolerance_ns``, monotonic per source (module docstring).

    ``max_age_ns`` (None: no age limit) also refuses stamps older than that on ``now_ns``.
    Raises ``ValueError`` on a negative tolerance or age.
    """

    future_tolerance_ns: int
    max_age_ns: int | None = None
    _last: dict = field(default_factory=dict, init=False, repr=False)

    def __post_init__(self):
        if int(self.future_tolerance_ns) != self.future_tolerance_ns \
                or self.future_tolerance_ns < 0:
            raise ValueError('future_tolerance_ns must be a whole number of ns >= 0, got '
                             f'{self.future_tolerance_ns!r}')
        if self.max_age_ns is not None and (int(self.max_age_ns) != self.max_age_ns
                                            or self.max_age_ns < 0):
            raise ValueError(f'max_age_ns must be None or a whole number of ns >= 0, got '
                             f'{self.max_age_ns!r}')

    def check(self, source: Hashable, stamp_ns: int, now_ns: int) -> StampCheck:
        """Judge ``stamp_ns`` from ``source`` at ``now_ns``; remember it if accepted."""
        stamp_ns, now_ns = int(stamp_ns), int(now_ns)
        last = self._last.get(source)
        if last is not None and stamp_ns <= last:
            verdict = StampVerdict.REPEAT if stamp_ns == last else StampVerdict.BACKWARDS
            return StampCheck(verdict, source, stamp_ns, last, stamp_ns - last)
        if stamp_ns - now_ns > self.future_tolerance_ns:
            verdict = StampVerdict.FUTURE
        elif self.max_age_ns is not None and now_ns - stamp_ns > self.max_age_ns:
            verdict = StampVerdict.TOO_OLD
        else:
            verdict = StampVerdict.ACCEPTED
            self._last[source] = stamp_ns
        return StampCheck(verdict, source, stamp_ns, now_ns, stamp_ns - now_ns)

    def last(self, source: Hashable) -> int | None:
        """Return the last stamp accepted from ``source`` (None if none)."""
        return self._last.get(source)

    def forget(self, source: Hashable | None = None) -> None:
        """Forget the last stamp of ``source`` (of every source if None): a time jump."""
        if source is None:
            self._last.clear()
        else:
            self._last.pop(source, None)
