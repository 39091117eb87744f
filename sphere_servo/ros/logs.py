"""
Throttled log lines that never hide a new problem.

rclpy's ``throttle_duration_sec`` throttles a call site: after a refusal of ``r_delta``, a
refusal of ``b`` in the next two seconds would not be logged at all. :class:`ThrottledLog`
throttles per *kind* of line: its text with the digits removed (``r_delta = -0.1 …`` and
``r_delta = -0.2 …`` are one kind, ``‖b‖ = 2.0 …`` another), so a flood of one problem is
logged once per ``period`` and a different problem at once.
"""
from __future__ import annotations

import re
import time

_DIGITS = re.compile(r'\d+')
MAX_KINDS = 256  # kinds remembered (the oldest are forgotten first)


def kind_of(text: str) -> str:
    """Return the kind of a log line: its text without the digits."""
    return _DIGITS.sub('', text)


class ThrottledLog:
    """Log a line at most once per ``period`` seconds (wall) per kind of line."""

    def __init__(self, logger, period: float = 1.0):
        self.logger = logger
        self.period = period
        self._last: dict[str, float] = {}

    def _due(self, text: str) -> bool:
        now, kind = time.monotonic(), kind_of(text)
        if now - self._last.get(kind, -float('inf')) < self.period:
            return False
        self._last.pop(kind, None)
        self._last[kind] = now
        if len(self._last) > MAX_KINDS:
            self._last.pop(next(iter(self._last)))
        return True

    def error(self, text: str) -> None:
        if self._due(text):
            self.logger.error(text)

    def warn(self, text: str) -> None:
        if self._due(text):
            self.logger.warn(text)

    def info(self, text: str) -> None:
        if self._due(text):
            self.logger.info(text)
