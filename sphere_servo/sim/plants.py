"""
What the headless closed loop servos (no ROS): a free-flying camera or the UR5 arm.

A plant holds the camera's pose and executes one twist per control period. The loop
(:func:`sphere_servo.sim.loop.closed_loop`) asks it for the target's pose in the camera to
observe, hands it the law's twist ``v_c`` (current camera frame, m/s and rad/s) and records
the camera pose ``oMc`` in the target frame o (the world of the loop) after each step.

- :class:`FreeCamera`  the camera moves by the exact exponential map
  ``oMc ← oMc · exp6(v_c dt)`` (no robot, no limits).
- :class:`ArmPlant`  the camera on the UR5's tool (:class:`~sphere_servo.sim.arm.ArmModel`):
  ``arm.command(v_c); arm.step(dt)``, ``cMo`` from the arm's kinematics. The arm's own step
  (DLS, limits, singularity slow-down) decides what the camera really does; the plant stops
  the run where the arm cannot follow (a joint limit, or a singularity holding the arm to a
  crawl).

Why a run ends is a :class:`LoopOutcome`; a plant that ends it says so with a
:class:`PlantStop`.
"""
from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

import numpy as np
import pinocchio as pin

from sphere_servo.core.geometry import integrate_camera
from sphere_servo.sim.arm import ArmModel, Status, TwistError

#: the arm counts as held by a singularity when every joint moves less than this per step
#: (100× below a slowed-down arm's motion) ...
SINGULAR_CRAWL = 1e-4
#: ... for this many steps in a row
SINGULAR_STEPS = 10
#: why an arm run stopped at a singularity (the outcome's detail)
SINGULAR_DETAIL = 'the arm stopped near a singular configuration'


class LoopOutcome(str, Enum):
    """Why a closed-loop run ended (the value starts the run's reason text)."""

    CONVERGED = 'converged'      # ‖s − s*‖₂ < tol
    MAX_ITER = 'max_iter'        # the iteration budget ran out first
    TARGET_LOST = 'target lost'  # the target could not be observed (or no valid twist)
    JOINT_LIMIT = 'joint_limit'  # the arm met a joint position limit
    SINGULARITY = 'singularity'  # a singularity held the arm to a crawl


@dataclass(frozen=True)
class PlantStop:
    """A plant ends the run: why, in words, and the joints at a limit (JOINT_LIMIT)."""

    outcome: LoopOutcome
    detail: str
    joints: tuple[str, ...] = ()


@dataclass(frozen=True)
class JointLimits:
    """Joint position limits (rad) in effect during an arm run, with the joints' names."""

    lower: np.ndarray
    upper: np.ndarray
    names: tuple[str, ...]


class FreeCamera:
    """A free-flying camera: the exact exponential map of each twist, nothing to stop it."""

    def __init__(self, cMo_start: pin.SE3, cMo_desired: pin.SE3):
        self._oMc = cMo_start.inverse()
        self._cMo_desired = cMo_desired

    def desired_cMo(self) -> pin.SE3:
        """Return the pose of the target in the camera at the desired pose (s* seen there)."""
        return self._cMo_desired

    def desired_oMc(self) -> np.ndarray:
        """Return the desired camera pose in the target frame (4, 4)."""
        return self._cMo_desired.inverse().homogeneous.copy()

    def cMo(self) -> pin.SE3:
        """Return the pose of the target in the current camera."""
        return self._oMc.inverse()

    def oMc(self) -> np.ndarray:
        """Return the current camera pose in the target frame (4, 4)."""
        return self._oMc.homogeneous.copy()

    def step(self, v_c: np.ndarray, dt: float) -> PlantStop | None:
        """Move the camera by ``exp6(v_c dt)`` (twist in the current camera frame)."""
        self._oMc = integrate_camera(self._oMc, v_c, dt)
        return None

    def record(self) -> dict:
        """Return the fields of the loop's result only this plant records (none)."""
        return {}


class ArmPlant:
    """
    The camera on the UR5: each twist is commanded to the arm, which steps ``dt``.

    The arm starts at rest at ``q_start``; the desired pose is the camera's at
    ``q_desired``. With ``stop_at_limit`` the run stops at the first step whose status is
    ``joint_limit`` (JOINT_LIMIT, detail: the arm's message naming the joints), or once a
    singularity has held the arm to a crawl (every joint < ``SINGULAR_CRAWL`` rad per step)
    for ``SINGULAR_STEPS`` steps (SINGULARITY): the arm slows down to its singularity
    threshold, which the twist keeps pushing it towards, so the image and the twist hardly
    change and the run would only wait for its iteration budget. Records the joint
    positions (N+1, nq), each step's :class:`~sphere_servo.sim.arm.Status` and the limits.
    """

    def __init__(self, arm: ArmModel, q_start: np.ndarray, q_desired: np.ndarray,
                 stop_at_limit: bool = True):
        self.arm = arm
        self.q_desired = np.asarray(q_desired, float)
        self.stop_at_limit = stop_at_limit
        arm.reset(q_start)
        self.joints = [arm.q.copy()]
        self.statuses: list[Status] = []
        self._held = 0  # consecutive steps a singularity held the arm to a crawl

    def desired_cMo(self) -> pin.SE3:
        """Return the pose of the target in the camera at ``q_desired`` (s* seen there)."""
        return self.arm.cMo(self.q_desired)

    def desired_oMc(self) -> np.ndarray:
        """Return the camera pose in the target frame at ``q_desired`` (4, 4)."""
        return self.arm.oMc(self.q_desired).homogeneous.copy()

    def cMo(self) -> pin.SE3:
        """Return the pose of the target in the current camera (the arm's kinematics)."""
        return self.arm.cMo()

    def oMc(self) -> np.ndarray:
        """Return the current camera pose in the target frame (4, 4)."""
        return self.arm.oMc().homogeneous.copy()

    def step(self, v_c: np.ndarray, dt: float) -> PlantStop | None:
        """
        Command ``v_c``, step the arm ``dt``; a :class:`PlantStop` if the run ends here.

        A twist the arm refuses (not finite, beyond its physical bound) ends the run
        (TARGET_LOST: no valid twist, the arm's reason as the detail) after a step at rest,
        recorded as any other: it is not an exception out of the loop, whose caller would
        take it for a target not observable from the start.
        """
        refused = None
        try:
            self.arm.command(v_c)
        except TwistError as exc:  # the arm has stopped
            refused = exc
        info = self.arm.step(dt)
        self.statuses.append(info.status)
        self.joints.append(self.arm.q.copy())
        if refused is not None:
            return PlantStop(LoopOutcome.TARGET_LOST, f'the arm refused the twist: {refused}')
        if not self.stop_at_limit:
            return None
        if info.status == Status.JOINT_LIMIT:
            return PlantStop(LoopOutcome.JOINT_LIMIT, info.message, tuple(info.joints))
        crawl = np.max(np.abs(self.joints[-1] - self.joints[-2])) < SINGULAR_CRAWL
        self._held = self._held + 1 if info.status == Status.SINGULARITY and crawl else 0
        if self._held >= SINGULAR_STEPS:
            return PlantStop(LoopOutcome.SINGULARITY, SINGULAR_DETAIL)
        return None

    def record(self) -> dict:
        """Return the joint positions, step statuses and joint limits of the run so far."""
        return {'joints': np.array(self.joints), 'arm_status': list(self.statuses),
                'joint_limits': JointLimits(self.arm.lower.copy(), self.arm.upper.copy(),
                                            tuple(self.arm.joint_names))}
