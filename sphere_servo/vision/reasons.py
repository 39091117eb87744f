"""
Why the detector found no target, or a mark: :class:`Reason` and :class:`NotDetected` (no ROS).

A miss is a reason (an enum, for code) and a detail (numbers, the failing check, for
people); ``str(NotDetected)`` is the message the nodes log. A mark's reason names the mark.
"""
from __future__ import annotations

from dataclasses import dataclass
from enum import Enum


class Reason(Enum):
    """Why the sphere (or a mark) was not detected; the value is the message."""

    NO_BLOB = 'no sphere-like blob'
    TOO_SMALL = 'largest blob too small'
    TOO_LARGE = 'target too large for the image'
    CUT_BY_BORDER = 'sphere cut by the border'
    NOT_BODY_COLOURED = 'blob is not body-coloured'
    NOT_ELLIPTICAL = 'blob is not elliptical'
    FEW_EDGE_POINTS = 'too few clean edge points'
    LOW_CONTRAST = 'blob contrast too low'
    EDGE_COVERAGE = 'blob rejected: its edge is not contrasted all around'
    RESIDUAL = 'blob rejected: fit residual'
    NOT_A_SPHERE = 'fitted conic is not a sphere image'
    MARKS_INCONSISTENT = 'blob rejected: its marks do not fit the target'
    AMBIGUOUS = 'several sphere-like blobs, none with a mark'
    COLOURS_SWAPPED = "the marks' colours are the target's with red and blue swapped"
    # a mark's reasons ({mark}: its name)
    MARK_NOT_FOUND = 'mark {mark} not found'
    MARK_FACES_AWAY = 'mark {mark} faces away from the camera'
    MARK_UNMEASURABLE = 'mark {mark} cut by the limb, too little of its rim to measure'
    MARK_CUT_BY_BORDER = 'mark {mark} cut by the image border'
    MARK_INCOMPLETE = 'mark {mark} seen only in part'
    MARK_OFF_SPHERE = 'mark {mark} lies outside the sphere'
    MARK_NOT_A_CAP = 'mark {mark} spreads beyond the cap its centre predicts'


@dataclass(frozen=True)
class NotDetected:
    """The sphere (or the mark ``mark``) was not found: the reason and a detail."""

    reason: Reason
    detail: str = ''
    mark: str = ''

    def __str__(self) -> str:
        text = self.reason.value.format(mark=self.mark) if self.mark else self.reason.value
        return text + (f' ({self.detail})' if self.detail else '')
