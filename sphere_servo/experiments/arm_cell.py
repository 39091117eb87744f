"""
The UR5 cell of the experiments: the arm placed as in ``config/params/arm_sim.yaml``, in the loop.

- :func:`make_arm`  the UR5 with the config's target placement, hand-eye and speed, and
  optionally a tighter safety limit on some joints (the robot cell of the joint-limit
  scenario).
- :func:`arm_start`  joint configurations of a start and a desired camera pose (IK).
- :func:`run_arm`  the headless closed loop with the arm as the plant
  (:class:`~sphere_servo.sim.plants.ArmPlant`).
- :func:`search_joint_limit_start`  the search that found the joint-limit scenario's start.
"""
from __future__ import annotations

import sys

import numpy as np
import pinocchio as pin

from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.geometry import GeometryError
from sphere_servo.core.targets import cc_target, Target
from sphere_servo.experiments.scenarios import camera_at, CMO_DESIRED, DT, PAPER_GAIN
from sphere_servo.sim.arm import ArmModel, pose_from_xyz_rpy
from sphere_servo.sim.loop import closed_loop, FeatureSetSpec, LoopResult
from sphere_servo.sim.observers import exact_observer
from sphere_servo.sim.plants import ArmPlant, LoopOutcome

#: arm placement of config/params/arm_sim.yaml: target in the world, hand-eye, IK seed, speed
ARM_KW = {'wMo': ([0.5, 0.1, 0.05], [np.pi, 0.0, -np.pi / 2]),
          'tool0Mc': ([0.0, -0.04, 0.02], [0.0, 0.0, 0.0]), 'velocity_scale': 0.5}
ARM_SEED = np.array([0.0, -1.57, 1.57, -1.57, -1.57, 0.0])


def make_arm(cell_limits: dict | None = None) -> ArmModel:
    """
    Build the UR5 placed as in ``config/params/arm_sim.yaml``.

    ``cell_limits`` {joint index: (lo, hi)} tightens the URDF position limits (None: keep
    that side).
    """
    arm = ArmModel(wMo=pose_from_xyz_rpy(*ARM_KW['wMo']),
                   tool0Mc=pose_from_xyz_rpy(*ARM_KW['tool0Mc']),
                   velocity_scale=ARM_KW['velocity_scale'])
    for j, (lo, hi) in (cell_limits or {}).items():
        arm.lower[j] = arm.lower[j] if lo is None else max(arm.lower[j], lo)
        arm.upper[j] = arm.upper[j] if hi is None else min(arm.upper[j], hi)
    return arm


def arm_start(arm: ArmModel, cMo_start: pin.SE3, cMo_desired: pin.SE3,
              turns=(0,) * 6) -> tuple[np.ndarray, np.ndarray]:
    """
    Return ``(q_start, q_desired)``: the IK of both poses.

    The start is seeded at the desired, plus ``turns`` whole turns on its joints. Raises
    ``GeometryError`` if a pose is unreachable or the winding leaves the joint limits.
    """
    qd, ok_d, _ = arm.ik_for_cMo(cMo_desired, ARM_SEED)
    qs, ok_s, _ = arm.ik_for_cMo(cMo_start, qd)
    if not (ok_d and ok_s):
        raise GeometryError("start or desired pose out of the arm's reach")
    qs = qs + 2 * np.pi * np.asarray(turns, float)
    qs = qs - 2 * np.pi * np.round((qs - qd) / (2 * np.pi)) * (np.asarray(turns) == 0)
    if np.any(qs < arm.lower) or np.any(qs > arm.upper):
        raise GeometryError('that winding is outside the joint limits')
    return qs, qd


def run_arm(target: Target, cMo_start: pin.SE3, cMo_desired: pin.SE3,
            feature_set: FeatureSetSpec = 's_n', r_hat: float | None = None,
            gain=PAPER_GAIN, dt: float = DT, max_iter: int = 600, tol: float = 1e-4,
            observer=None, camera: CameraIntrinsics | None = None, turns=(0,) * 6,
            arm: ArmModel | None = None, stop_at_limit: bool = True,
            cell_limits: dict | None = None) -> LoopResult:
    """
    Servo with the UR5 in the loop: twist → ``arm.command(v); arm.step(dt)``.

    ``cMo`` comes from the arm's kinematics; the desired pose is the arm's at the IK of
    ``cMo_desired``. ``arm`` (default :func:`make_arm` with ``cell_limits``) is reset to
    the start. Stops at convergence or, with ``stop_at_limit``, where
    :class:`~sphere_servo.sim.plants.ArmPlant` stops (a joint limit, a singularity holding
    the arm to a crawl). The observer defaults to the exact image through ``camera``; the
    result records ``in_view`` through ``camera`` (default :class:`CameraIntrinsics`), the
    joints, the arm's step statuses and its joint limits.
    """
    arm = arm or make_arm(cell_limits)
    qs, qd = arm_start(arm, cMo_start, cMo_desired, turns)
    observer = observer or exact_observer(target, camera)
    plant = ArmPlant(arm, qs, qd, stop_at_limit=stop_at_limit)
    return closed_loop(plant, target, feature_set, r_hat=r_hat, gain=gain, dt=dt,
                       max_iter=max_iter, tol=tol, observer=observer,
                       camera=camera or CameraIntrinsics())


def cell_limits_text(limits: dict, names) -> str:
    """
    Describe cell limits {joint index: (lo, hi)}, e.g. 'elbow_joint ≤ 2.04 rad'.

    ``names`` are the arm's joint names.
    """
    parts = []
    for j, (lo, hi) in sorted(limits.items()):
        if lo is not None and hi is not None:
            parts.append(f'{names[j]} ∈ [{lo}, {hi}] rad')
        elif hi is not None:
            parts.append(f'{names[j]} ≤ {hi} rad')
        elif lo is not None:
            parts.append(f'{names[j]} ≥ {lo} rad')
    return ', '.join(parts)


def search_joint_limit_start(n: int = 300, seed: int = 5, out=sys.stdout) -> list:
    """
    Search for a start from which s_cc drives the UR5 into a joint limit while s_n converges.

    Exact observation, for speed. Samples ``n`` start poses (distance 0.3–0.6 m, direction
    on the marked side, roll ±150°), runs both sets on the UR5 with its own limits, and for
    each joint and side measures how far each set's joint trajectory overshoots the
    interval between its start and final values. Returns candidates
    ``(gap_rad, eye, roll_deg, joint, side, limit_rad)`` sorted by the gap between s_cc's
    and s_n's overshoot: a safety limit at ``limit_rad`` (mid-gap) is crossed by s_cc only.
    Starts where either set meets the UR5's own limits are reported too (gap ∞). Starts
    where the two sets end a whole turn apart on a joint (a roll near 180° that they turn
    opposite ways round: a winding, not a detour) are left out.
    """
    rng = np.random.default_rng(seed)
    target, arm = cc_target(), make_arm()
    found = []
    for _ in range(n):
        d = rng.uniform(0.3, 0.6)
        u = rng.normal(size=3)
        u[2] = -abs(u[2]) - 0.7
        eye = np.round(d * u / np.linalg.norm(u), 3)
        roll = float(np.round(rng.uniform(-150, 150)))
        try:
            runs = {fs: run_arm(target, camera_at(eye, roll), CMO_DESIRED, fs, arm=arm)
                    for fs in ('s_cc', 's_n')}
        except GeometryError:
            continue
        scc, sn = runs['s_cc'], runs['s_n']
        if scc.outcome is LoopOutcome.JOINT_LIMIT and sn.converged:
            found.append((np.inf, eye.tolist(), roll, None, None, None))
        if not (scc.converged and sn.converged):
            continue
        if np.abs(scc.joints[-1] - sn.joints[-1]).max() > np.pi:
            continue
        J = sn.joints
        for j in range(J.shape[1]):
            for side in (1, -1):
                ref = side * max(side * J[0, j], side * J[-1, j])
                over = {fs: side * (side * r.joints[:, j]).max() - ref
                        for fs, r in runs.items()}
                o_n, o_cc = side * over['s_n'], side * over['s_cc']
                gap = o_cc - max(o_n, 0.0)
                if gap > 0.05:
                    limit = ref + side * (max(o_n, 0.0) + 0.5 * gap)
                    found.append((float(gap), eye.tolist(), roll, j, side, float(limit)))
    found.sort(key=lambda f: -f[0])
    for f in found[:5]:
        out.write(f'  gap {f[0]:.3f} rad: eye={f[1]} roll={f[2]} joint={f[3]} side={f[4]} '
                  f'limit={f[5]}\n')
    return found
