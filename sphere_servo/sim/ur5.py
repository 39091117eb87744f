"""
Where the UR5's URDF is found, and poses as ``[x y z roll pitch yaw]`` (no ROS).

:func:`find_ur5_urdf` looks for ``example-robot-data``'s ``ur5_robot.urdf`` (the PyPI wheel
or a full ROS install); :func:`pose_from_xyz_rpy` / :func:`pose_to_xyz_rpy` convert a pose
to and from the six numbers the parameters carry.
"""
from __future__ import annotations

import glob
import os
from pathlib import Path
import sys

import numpy as np
import pinocchio as pin

URDF_ENV = 'SPHERE_SERVO_UR5_URDF'
URDF_REL = 'example-robot-data/robots/ur_description/urdf/ur5_robot.urdf'


def find_ur5_urdf(override: str | os.PathLike | None = None) -> str:
    """
    Path of ``ur5_robot.urdf``.

    Looked for, in this order: ``override``; the environment variable
    ``SPHERE_SERVO_UR5_URDF``; ``cmeel.prefix/share/…`` under ``sys.prefix`` and every
    ``site-packages`` on ``sys.path`` (the PyPI ``example-robot-data`` wheel); the
    ``example-robot-data`` share directory of an ament (full ROS) install. Raises
    ``FileNotFoundError`` listing the places searched.
    """
    tried = []
    for cand in (override, os.environ.get(URDF_ENV)):
        if cand:
            if Path(cand).is_file():
                return str(cand)
            tried.append(str(cand))
            if cand is override:
                raise FileNotFoundError(f'UR5 URDF not found at the given path {cand!r}')
    roots = [sys.prefix, *[p for p in sys.path if p.endswith('-packages')]]
    for root in roots:
        for pattern in (f'{root}/cmeel.prefix/share/{URDF_REL}',
                        f'{root}/lib*/python*/site-packages/cmeel.prefix/share/{URDF_REL}'):
            hits = sorted(glob.glob(pattern))
            if hits:
                return hits[0]
            tried.append(pattern)
    try:  # a full ROS install (ros-jazzy-example-robot-data)
        from ament_index_python.packages import get_package_share_directory
        share = Path(get_package_share_directory('example-robot-data'))
        cand = share / 'robots/ur_description/urdf/ur5_robot.urdf'
        if cand.is_file():
            return str(cand)
        tried.append(str(cand))
    except Exception:  # noqa: BLE001 - ament index absent or package unknown
        tried.append('ament index: example-robot-data')
    raise FileNotFoundError(
        'UR5 URDF (example-robot-data) not found; install it with '
        '`pip install example-robot-data` or set SPHERE_SERVO_UR5_URDF. Searched: '
        + '; '.join(tried))


def pose_from_xyz_rpy(xyz, rpy) -> pin.SE3:
    """SE3 from a translation and roll-pitch-yaw (``R = Rz(yaw) Ry(pitch) Rx(roll)``)."""
    return pin.SE3(pin.rpy.rpyToMatrix(*np.asarray(rpy, dtype=float)),
                   np.asarray(xyz, dtype=float))


def pose_to_xyz_rpy(M: pin.SE3) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`pose_from_xyz_rpy`."""
    return np.array(M.translation), np.asarray(pin.rpy.matrixToRpy(M.rotation))
