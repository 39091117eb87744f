# noqa: A005 - imported only as sphere_servo.core.types, so it never shadows the stdlib
"""
Shape-typed ndarray aliases shared by every layer (documentation only; no runtime check).

Frames are named in variables (``cMo``: the target frame o in the camera frame c), so the
aliases say shapes and units, not frames.
"""
from __future__ import annotations

import numpy as np

Vec2 = np.ndarray     # (2,)
Vec3 = np.ndarray     # (3,), e.g. a unit ray q or the centre direction b (camera frame)
Mat3 = np.ndarray     # (3, 3), a rotation aRb or a conic C
Twist = np.ndarray    # (6,), (v, ω) in the current camera frame, m/s and rad/s
Points2 = np.ndarray  # (N, 2), image points (pixels or normalized coordinates)
Points3 = np.ndarray  # (N, 3), points or unit rays
Conic = np.ndarray    # (3, 3) symmetric, x̄ᵀ C x̄ = 0
Image = np.ndarray    # (H, W, 3) or (H, W) uint8
