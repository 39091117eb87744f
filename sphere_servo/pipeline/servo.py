"""The servo's logic without ROS (issue 12: the node becomes a thin adapter around it).

:class:`ServoState` is what the servo reports; its values are the strings published in the
servo's status message, so a supervisor compares with ``ServoState.CONVERGED.value`` and
never with a literal.
"""
from __future__ import annotations

from enum import Enum


class ServoState(str, Enum):
    """What the servo is doing (the value is the published status text)."""

    WAITING = 'waiting'          # no features yet
    DISABLED = 'disabled'        # features come, the servo is not enabled: zero twists
    SERVOING = 'servoing'        # a twist from the law
    CONVERGED = 'converged'      # ‖s − s*‖ < tol: zero twist
    TARGET_LOST = 'target lost'  # the target or a mark lost, or no valid twist: zero twist
    STALE = 'stale'              # no usable features for longer than the timeout: zero twist
