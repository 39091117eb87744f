"""Named camera poses of the paper-style scenarios (no ROS), shared by the demo, the tests
and the paper runner. Poses are ``cMo`` (target in the camera optical frame)."""
from __future__ import annotations

import numpy as np
import pinocchio as pin

from sphere_servo.core.geometry import exp3, look_at

#: desired pose: 0.45 m in front of the marked (−z) cap, looking along the target's +z
CMO_DESIRED = pin.SE3(np.eye(3), np.array([0.0, 0.0, 0.45]))


def camera_at(eye, roll_deg: float = 0.0, aim=(0.0, 0.0, 0.0)) -> pin.SE3:
    """``cMo`` of a camera at ``eye`` (target frame, m) aimed at ``aim``, rolled about its
    optical axis by ``roll_deg`` (deg)."""
    oMc = look_at(np.asarray(eye, float), np.asarray(aim, float), up=(0.0, -1.0, 0.0))
    return (oMc * pin.SE3(exp3([0.0, 0.0, np.radians(roll_deg)]), np.zeros(3))).inverse()


#: a large displacement from CMO_DESIRED (21.7 cm, 120.7°) with both marks visible
CMO_FAR_START = camera_at([0.15, -0.12, -0.35], roll_deg=65.0)
