"""
The simulated UR5 with an eye-in-hand camera (pure model, no ROS).

- Robot: the UR5 URDF of ``example-robot-data`` (:func:`find_ur5_urdf`), with Pinocchio.
- Camera: the optical frame ``c`` (REP 103: z forward, x right, y down) on ``tool0`` by the
  hand-eye ``tool0Mc``; ``tool0``'s z is the flange's outward axis: ``I`` looks out of it.
- Command: a camera twist ``v_c = (v, ω)`` expressed in the *current camera frame*
  (DESIGN.md §1). It is mapped to joint velocities by damped least squares on the camera
  Jacobian ``J_c`` (``pin.LOCAL`` on the added camera frame, 6×nv), with damping that grows
  as the smallest singular value ``σ_min`` of ``J_c`` falls below ``singular_threshold``.
  Then, in this order:

  1. joint position limits: a joint at a limit that the solution would drive further is
     locked and the least-squares problem is solved again without it (it may still move
     away from the limit); status ``joint_limit`` (details: the joint names);
  2. singularity: when ``σ_min < singular_threshold`` the solution is damped, so the
     camera departs from the command (less motion along the weak directions): status
     ``singularity``, whichever way it moves; motion that decreases ``σ_min`` is also slowed
     linearly down to 0 at ``singular_stop`` (MoveIt Servo's rule, on ``σ_min``);
  3. joint velocity limits (URDF × ``velocity_scale``): the whole vector is scaled by one
     factor, never clipped per axis, so the camera keeps the commanded direction;
  4. a joint that would cross its limit within this step is landed exactly on it, again
     by scaling the whole vector.

- Integration: ``q ← pin.integrate(model, q, q̇ dt)`` with a fixed ``dt``.
- Watchdog: if no command arrived for more than ``cmd_timeout`` seconds of simulated time,
  ``q̇ = 0`` and status ``timeout``.
- Refusals (:class:`TwistError`, a ``ValueError`` with a typed ``violation``): a twist not
  6 finite numbers, or beyond the physical bound ``twist_limit = (v, ω)``, is refused
  *before* anything is integrated and the arm stops at once (zero velocity from the next
  step). The bound: the smaller of ``MAX_LINEAR_SPEED`` / ``MAX_ANGULAR_SPEED`` and
  ``TWIST_FACTOR`` × the arm's fastest camera motion (:attr:`ArmModel.reach_speed`); UR5:
  ``‖v‖ ≤ 100 m/s``, ``‖ω‖ ≤ 190.5 rad/s``, above the servo's own bounds (``v_max ≤ 10``,
  ``w_max ≤ 100``), so a servo within them is never refused.
- Error state: :meth:`ArmModel.step` never integrates an invalid state: a ``q`` or ``q̇``
  not finite, or ``q`` past a limit by more than ``LIMIT_TOL``, holds the arm still with
  status ``error``, every twist refused (``Bound.STATE``) until :meth:`ArmModel.reset`.
- Ground truth: ``wMc`` (camera in the world), ``cMo`` (target in the camera), ``wMo``.

Stopping distance (numbers for the UR5: README, Safety). No acceleration limit: after a
refused twist the next step is at rest, so the motion after it is at most the period already
running, ``|Δq_i| ≤ q̇max_i dt``; after the last command the watchdog stops the arm after
:meth:`ArmModel.watchdog_steps` = ``⌊cmd_timeout/dt⌋ + 1`` steps (the first step whose
start is more than ``cmd_timeout`` after the command is at rest: 7 steps = 0.233 s for
0.2 s at 30 Hz).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum
import math

import numpy as np
import pinocchio as pin

from sphere_servo.core.geometry import GeometryError
from sphere_servo.core.validation import Bound, check_array, refuse, Violation
# the URDF and pose helpers: re-exported, their callers know them from here
from sphere_servo.sim.ur5 import (find_ur5_urdf, pose_from_xyz_rpy,  # noqa: F401
                                  pose_to_xyz_rpy, URDF_ENV, URDF_REL)

CAMERA_FRAME = 'camera_optical_frame'
#: absolute twist bounds: 10× the fastest (delta) robots' ~10 m/s; 10× six 3.2 rad/s joints
MAX_LINEAR_SPEED = 100.0    # m/s
MAX_ANGULAR_SPEED = 200.0   # rad/s
#: a twist is refused beyond this many times the fastest motion the arm itself can make
TWIST_FACTOR = 10.0
#: how far (rad) q may pass a limit before the state is invalid: round-off (step 4 lands)
LIMIT_TOL = 1e-9
#: slack (s) on ``cmd_timeout``: summed periods' round-off (6 × 1/30 s > 0.2 s in floats)
TIME_TOL = 1e-9


class Status(str, Enum):
    """Status of the last simulation step (the string value is what the node publishes)."""

    OK = 'ok'
    JOINT_LIMIT = 'joint_limit'
    SINGULARITY = 'singularity'
    TIMEOUT = 'timeout'
    ERROR = 'error'  # the state became invalid: held still, commands refused until reset


class TwistError(GeometryError):
    """A camera twist refused by the arm (``violation`` says which bound); the arm stops."""


@dataclass
class StepInfo:
    """
    What the last mapping/step did.

    status   the most important condition (error > timeout > joint_limit > singularity > ok).
    joints   names of the joints locked at a position limit (for ``joint_limit``).
    qdot     the joint velocities applied (nv,).
    scale    the uniform factor applied to q̇ (velocity limits, singularity, limit landing).
    sigma_min  smallest singular value of the camera Jacobian at the start of the step.
    flags    every condition met (a set of :class:`Status`).
    error    what made the state invalid (for ``error``).
    """

    status: Status = Status.OK
    joints: list = field(default_factory=list)
    qdot: np.ndarray = field(default_factory=lambda: np.zeros(0))
    scale: float = 1.0
    sigma_min: float = float('nan')
    flags: set = field(default_factory=set)
    error: Violation | None = None

    @property
    def message(self) -> str:
        """Human-readable details, e.g. ``'wrist_3_joint at limit'``."""
        if self.status == Status.ERROR:
            return f'invalid state, holding still until reset: {self.error}'
        if self.status == Status.JOINT_LIMIT:
            return ', '.join(self.joints) + ' at position limit'
        if self.status == Status.SINGULARITY:
            return f'near singularity: sigma_min={self.sigma_min:.4f}, scale={self.scale:.3f}'
        if self.status == Status.TIMEOUT:
            return 'no command within cmd_timeout: holding still'
        return ''


class ArmModel:
    """
    UR5 + eye-in-hand camera kinematics, DLS command mapping, limits and a watchdog.

    Parameters
    ----------
    urdf_path      see :func:`find_ur5_urdf`.
    tool0Mc        hand-eye transform (pose of the camera optical frame in ``tool0``).
    wMo            pose of the target frame in the world (the robot base frame ``world``).
    q0             start joint configuration (nq,); the neutral one by default.
    damping        maximum DLS damping λ_max (rad/s per m/s); applied fully at σ_min = 0.
    singular_threshold   σ_min under which damping and slow-down start.
    singular_stop  σ_min at which motion towards the singularity stops.
    velocity_scale fraction of the URDF joint velocity limits used (0, 1].
    cmd_timeout    watchdog timeout, seconds of simulated time.
    limit_margin   distance (rad) to a position limit within which a joint counts as at it.

    """

    def __init__(self, urdf_path=None, tool0Mc: pin.SE3 | None = None,
                 wMo: pin.SE3 | None = None, q0=None, damping: float = 0.05,
                 singular_threshold: float = 0.04, singular_stop: float = 0.01,
                 velocity_scale: float = 1.0, cmd_timeout: float = 0.5,
                 limit_margin: float = 1e-6, ee_frame: str = 'tool0'):
        for name, val, lo in (('damping', damping, 0.0), ('cmd_timeout', cmd_timeout, 0.0),
                              ('singular_stop', singular_stop, 0.0)):
            if not np.isfinite(val) or val < lo:
                raise ValueError(f'{name} must be a finite number >= {lo}, got {val}')
        if not (np.isfinite(velocity_scale) and 0 < velocity_scale <= 1):
            raise ValueError(f'velocity_scale must be in (0, 1], got {velocity_scale}')
        if not (np.isfinite(singular_threshold) and singular_threshold > singular_stop):
            raise ValueError('singular_threshold must be finite and > singular_stop, got '
                             f'{singular_threshold} <= {singular_stop}')
        self.urdf_path = find_ur5_urdf(urdf_path)
        self.model = pin.buildModelFromUrdf(self.urdf_path)
        if not self.model.existFrame(ee_frame):
            raise ValueError(f'frame {ee_frame!r} not in the URDF')
        self.ee_frame = ee_frame
        self.tool0Mc = pin.SE3.Identity() if tool0Mc is None else pin.SE3(tool0Mc)
        ee_id = self.model.getFrameId(ee_frame)
        ee = self.model.frames[ee_id]
        self.cam_id = self.model.addFrame(pin.Frame(
            CAMERA_FRAME, ee.parentJoint, ee_id, ee.placement * self.tool0Mc,
            pin.FrameType.OP_FRAME))
        self.data = self.model.createData()
        self.joint_names = list(self.model.names)[1:]
        self.lower = np.array(self.model.lowerPositionLimit)
        self.upper = np.array(self.model.upperPositionLimit)
        self.vmax = np.array(self.model.velocityLimit) * velocity_scale
        self.damping = float(damping)
        self.singular_threshold = float(singular_threshold)
        self.singular_stop = float(singular_stop)
        self.cmd_timeout = float(cmd_timeout)
        self.limit_margin = float(limit_margin)
        self.wMo = pin.SE3.Identity() if wMo is None else pin.SE3(wMo)
        self.reach_speed = self._reach_speed()
        self.twist_limit = (min(MAX_LINEAR_SPEED, TWIST_FACTOR * self.reach_speed[0]),
                            min(MAX_ANGULAR_SPEED, TWIST_FACTOR * self.reach_speed[1]))
        self.q_start = self.check_q(pin.neutral(self.model) if q0 is None else q0, 'q0')
        self.named: dict[str, np.ndarray] = {'start': self.q_start.copy()}
        self.reset()

    # --- state ----------------------------------------------------------------------
    def check_q(self, q, what='q') -> np.ndarray:
        """Return ``q`` as an (nq,) array, or ValueError: not finite, or past a limit."""
        q = np.asarray(q, dtype=float).ravel()
        if q.shape != (self.model.nq,):
            raise ValueError(f'{what} must have {self.model.nq} joint values '
                             f'({", ".join(self.joint_names)}), got {q.size}')
        if not np.all(np.isfinite(q)):
            raise ValueError(f'{what} contains NaN or inf: {q}')
        bad = [f'{n} = {v:.6g} not in [{lo:.6g}, {hi:.6g}]'
               for n, v, lo, hi in zip(self.joint_names, q, self.lower, self.upper)
               if not lo <= v <= hi]
        if bad:
            raise ValueError(f'{what} is outside the joint position limits: {"; ".join(bad)}')
        return q.copy()

    def _reach_speed(self) -> tuple[float, float]:
        """
        Bound the camera's speed at the URDF joint speed limits: ``(‖v‖max, ‖ω‖max)``.

        For revolute joints (the UR5's) ``v_c = Σ q̇_i a_i × r_i`` and ``ω_c = Σ q̇_i a_i``
        with ``‖r_i‖`` (joint i's axis to the camera) at most the sum ``L_i`` of the
        placements' lengths from joint i to the camera frame, in any configuration; so
        ``‖v‖ ≤ Σ q̇max_i L_i`` and ``‖ω‖ ≤ Σ q̇max_i`` (UR5: 11.2 m/s, 19.05 rad/s).
        """
        vlim = np.array(self.model.velocityLimit)
        frame = self.model.frames[self.cam_id]
        j, length = frame.parentJoint, float(np.linalg.norm(frame.placement.translation))
        v = w = 0.0
        while j > 0:
            i = self.model.idx_vs[j]
            v += float(vlim[i]) * length
            w += float(vlim[i])
            length += float(np.linalg.norm(self.model.jointPlacements[j].translation))
            j = self.model.parents[j]
        return v, w

    def watchdog_steps(self, dt: float) -> int:
        """Count the steps run under a command: ⌊cmd_timeout/dt⌋ + 1 (:meth:`fresh` at start)."""
        return int(math.floor((self.cmd_timeout + TIME_TOL) / dt)) + 1

    def fresh(self, t_cmd: float | None) -> bool:
        """Tell whether a command taken at ``t_cmd`` still runs: ``t − t_cmd ≤ cmd_timeout``."""
        return t_cmd is not None and self.t - t_cmd <= self.cmd_timeout + TIME_TOL

    def reset(self, q=None) -> None:
        """Back to the start configuration (or ``q``), at rest, time 0, no command, no error."""
        self.q = self.check_q(self.q_start if q is None else q)
        self.qdot = np.zeros(self.model.nv)
        self.t = 0.0
        self._cmd = np.zeros(6)
        self._cmd_time: float | None = None
        self.error: Violation | None = None
        self.info = StepInfo(qdot=self.qdot.copy())

    def set_q(self, q) -> None:
        """Jump to a joint configuration: at rest, its own status (an error stays), time kept."""
        self.q = self.check_q(q)
        self.qdot = np.zeros(self.model.nv)
        self.info = (self._error_info() if self.error is not None else
                     StepInfo(qdot=self.qdot.copy(), sigma_min=self.sigma_min()))

    # --- kinematics -----------------------------------------------------------------
    def wMc(self, q=None) -> pin.SE3:
        """Pose of the camera optical frame in the world."""
        q = self.q if q is None else q
        pin.framesForwardKinematics(self.model, self.data, q)
        return pin.SE3(self.data.oMf[self.cam_id])

    def cMo(self, q=None) -> pin.SE3:
        """Pose of the target in the camera frame (ground truth)."""
        return self.wMc(q).inverse() * self.wMo

    def oMc(self, q=None) -> pin.SE3:
        """Pose of the camera in the target frame (ground truth)."""
        return self.wMo.inverse() * self.wMc(q)

    def camera_jacobian(self, q=None) -> np.ndarray:
        """6×nv ``J_c``: ``v_c = J_c q̇`` with ``v_c = (v, ω)`` in the camera frame."""
        q = self.q if q is None else q
        return np.array(pin.computeFrameJacobian(self.model, self.data, q, self.cam_id,
                                                 pin.LOCAL))

    def sigma_min(self, q=None) -> float:
        return float(np.linalg.svd(self.camera_jacobian(q), compute_uv=False)[-1])

    def _dls(self, J: np.ndarray, v: np.ndarray, sigma_min: float,
             free: np.ndarray | None = None) -> np.ndarray:
        """
        Damped least squares ``Jᵀ(JJᵀ + λ²I)⁻¹ v`` (Nakamura–Chiaverini).

        λ² = λ_max²(1 − (σ/σ₀)²) below σ₀ = singular_threshold, 0 above. ``free``: the
        joints not locked at a limit; then ``(J_fᵀJ_f + λ²I)⁻¹ J_fᵀ v`` on their columns,
        a regular matrix (``J_f J_fᵀ`` lost a rank per locked joint, and 4 digits).
        """
        lam2 = 0.0
        if sigma_min < self.singular_threshold:
            lam2 = self.damping ** 2 * (1.0 - (sigma_min / self.singular_threshold) ** 2)
        if free is None or free.all():
            A = J @ J.T + (lam2 + 1e-12) * np.eye(J.shape[0])
            return J.T @ np.linalg.solve(A, v)
        qdot = np.zeros(J.shape[1])
        if free.any():
            Jf = J[:, free]
            qdot[free] = np.linalg.solve(Jf.T @ Jf + (lam2 + 1e-12) * np.eye(Jf.shape[1]),
                                         Jf.T @ v)
        return qdot

    # --- command mapping ----------------------------------------------------------------
    def twist_to_qdot(self, v_c, dt: float | None = None) -> StepInfo:
        """
        Joint velocities realising camera twist ``v_c`` at the current configuration.

        Limits are applied (see the module docstring). ``dt`` (if given) lands joints
        exactly on limits they would cross within the step. Raises :class:`TwistError` (a
        ``ValueError``) on a twist that :meth:`check_twist` refuses.
        """
        v_c = self.check_twist(v_c)
        info = StepInfo()
        J = self.camera_jacobian()
        info.sigma_min = float(np.linalg.svd(J, compute_uv=False)[-1])
        if not np.any(v_c):
            info.qdot = np.zeros(self.model.nv)
            return info
        # 1. position limits: lock joints pushed further into a limit, solve again
        locked = np.zeros(self.model.nv, dtype=bool)
        at_hi = self.q >= self.upper - self.limit_margin
        at_lo = self.q <= self.lower + self.limit_margin
        for _ in range(self.model.nv):
            qdot = self._dls(J, v_c, info.sigma_min, ~locked)
            push = ((at_hi & (qdot > 0)) | (at_lo & (qdot < 0))) & ~locked
            if not push.any():
                break
            locked |= push
        if locked.any():
            info.flags.add(Status.JOINT_LIMIT)
            info.joints = [n for n, lk in zip(self.joint_names, locked) if lk]
        # 2. singularity: the solution is damped (the camera no longer follows the command
        # exactly: always reported), and motion that decreases σ_min is slowed
        scale = 1.0
        if info.sigma_min < self.singular_threshold:
            info.flags.add(Status.SINGULARITY)
            eps = 1e-4 / max(np.linalg.norm(qdot), 1e-9)
            s_next = self.sigma_min(pin.integrate(self.model, self.q, qdot * eps))
            if s_next < info.sigma_min:
                ramp = ((info.sigma_min - self.singular_stop)
                        / (self.singular_threshold - self.singular_stop))
                scale = float(np.clip(ramp, 0.0, 1.0))
        qdot = qdot * scale
        # 3. velocity limits: one factor for the whole vector
        over = np.max(np.abs(qdot) / self.vmax)
        if over > 1.0:
            qdot /= over
            scale /= over
        # 4. do not cross a position limit within this step: land on it
        if dt is not None and dt > 0:
            q_next = self.q + qdot * dt
            room = np.where(qdot > 0, self.upper - self.q, self.lower - self.q)
            cross = ((q_next > self.upper) | (q_next < self.lower)) & (qdot != 0)
            if cross.any():
                f = float(np.min(np.clip(room[cross] / (qdot[cross] * dt), 0.0, 1.0)))
                qdot *= f
                scale *= f
                info.flags.add(Status.JOINT_LIMIT)
                info.joints = sorted(set(info.joints) | {
                    n for n, c in zip(self.joint_names, cross) if c},
                    key=self.joint_names.index)
        info.qdot, info.scale = qdot, scale
        info.status = (Status.JOINT_LIMIT if Status.JOINT_LIMIT in info.flags else
                       Status.SINGULARITY if Status.SINGULARITY in info.flags else Status.OK)
        return info

    def command(self, v_c) -> None:
        """
        Set the camera twist to execute from now on (stamped with the sim time).

        Refused with :class:`TwistError` (whose ``violation`` names the bound), *after*
        stopping the arm (zero velocity from the next step): a twist that is not 6 finite
        numbers, ``‖v‖ > twist_limit[0]`` m/s or ``‖ω‖ > twist_limit[1]`` rad/s (see the
        module docstring), and any twist while the arm is in the ``error`` state.
        """
        try:
            if self.error is not None:
                refuse(TwistError, 'camera twist', 'any', Bound.STATE,
                       f'none while the arm is in error ({self.error}): reset first')
            v_c = self.check_twist(v_c)
        except TwistError:
            self.stop()
            raise
        self._cmd = v_c.copy()
        self._cmd_time = self.t

    def check_twist(self, v_c) -> np.ndarray:
        """
        Return ``v_c`` as a (6,) array, or refuse it with :class:`TwistError`.

        6 finite numbers with ``‖v‖ ≤ twist_limit[0]`` m/s and ``‖ω‖ ≤ twist_limit[1]`` rad/s.
        """
        try:  # the common case first, in floats: NaN and inf fail the comparisons
            a = np.asarray(v_c, dtype=float).ravel()
            x, y, z, wx, wy, wz = a.tolist()
            if (math.hypot(x, y, z) <= self.twist_limit[0]
                    and math.hypot(wx, wy, wz) <= self.twist_limit[1]):
                return a
        except (TypeError, ValueError):
            pass
        v_c = check_array(TwistError, 'camera twist', np.ravel(v_c), (6,))
        for name, part, lim, unit in (('‖v‖', v_c[:3], self.twist_limit[0], 'm/s'),
                                      ('‖ω‖', v_c[3:], self.twist_limit[1], 'rad/s')):
            n = math.hypot(*part)  # no overflow for a finite twist
            if not n <= lim:
                refuse(TwistError, f'{name} of the camera twist', n, Bound.RANGE,
                       f'≤ {lim:.4g} {unit}: {TWIST_FACTOR:g}× the fastest the arm can '
                       'move, or the absolute bound')
        return v_c

    def stop(self) -> None:
        """Drop the current command (the arm halts at the next step)."""
        self._cmd = np.zeros(6)

    def step(self, dt: float) -> StepInfo:
        """
        Advance the simulation by ``dt`` seconds under the current command.

        Never integrates an invalid state: a non-finite ``q`` or ``q̇``, or a ``q`` beyond
        the position limits by more than ``LIMIT_TOL``, puts the arm in the ``error`` state
        (held still, time still advancing) until :meth:`reset`.
        """
        if not (np.isfinite(dt) and dt > 0):
            raise ValueError(f'dt must be a finite number > 0, got {dt}')
        if self.error is None:
            self._check_state(self.q, 'joint positions q')
        if self.error is not None:
            info = self._error_info()
        elif not self.fresh(self._cmd_time):
            info = StepInfo(status=Status.TIMEOUT, qdot=np.zeros(self.model.nv),
                            scale=0.0, flags={Status.TIMEOUT})
            if self._cmd_time is None:  # never commanded: idle, not a fault
                info = StepInfo(qdot=np.zeros(self.model.nv))
        else:
            info = self.twist_to_qdot(self._cmd, dt)
        if np.any(info.qdot):
            q = None
            if np.all(np.isfinite(info.qdot)):
                q = pin.integrate(self.model, self.q, info.qdot * dt)
            if self._check_state(q, 'integrated q', info.qdot):
                self.q = np.clip(q, self.lower, self.upper)  # round-off only (step 4 lands)
            else:
                info = self._error_info()
        self.qdot = info.qdot
        self.t += dt
        self.info = info
        return info

    def _check_state(self, q, what: str, qdot=None) -> bool:
        """Tell whether ``q`` (and ``qdot``) are a valid state; if not, enter ``error``."""
        if (q is not None and (qdot is None or math.isfinite(float(qdot @ qdot)))
                and float(np.max(np.maximum(self.lower - q, q - self.upper))) <= LIMIT_TOL):
            return True  # the common case in one pass: NaN fails the comparison
        if qdot is not None and not np.all(np.isfinite(qdot)):
            self._fail(Violation('joint velocities q̇', np.asarray(qdot), Bound.FINITE))
        elif q is None or not np.all(np.isfinite(q)):
            self._fail(Violation(what, np.asarray(q), Bound.FINITE))
        else:
            out = np.maximum(self.lower - q, q - self.upper)
            if np.any(out > LIMIT_TOL):
                i = int(np.argmax(out))
                self._fail(Violation(f'{self.joint_names[i]} position', float(q[i]),
                                     Bound.RANGE, f'[{self.lower[i]:g}, {self.upper[i]:g}] '
                                     f'rad within {LIMIT_TOL:g}'))
        return self.error is None

    def _fail(self, violation: Violation) -> None:
        self.error = violation
        self._cmd = np.zeros(6)

    def _error_info(self) -> StepInfo:
        return StepInfo(status=Status.ERROR, qdot=np.zeros(self.model.nv), scale=0.0,
                        flags={Status.ERROR}, error=self.error)

    # --- inverse kinematics -------------------------------------------------------------
    def solve_ik(self, wMc_des: pin.SE3, q_seed=None, tol: float = 1e-6,
                 max_iter: int = 500, damping: float = 1e-3) -> tuple[np.ndarray, bool, float]:
        """
        Joint configuration putting the camera at ``wMc_des``; does not move the arm.

        DLS iterated on the camera-frame error ``log6(wMc⁻¹ wMc_des)`` from ``q_seed``
        (current q by default), kept within the position limits. Returns
        ``(q, converged, error_norm)``.
        """
        q = self.q.copy() if q_seed is None else self.check_q(q_seed, 'q_seed')
        err = np.inf
        for _ in range(max_iter):
            e = np.array(pin.log6(self.wMc(q).inverse() * wMc_des).vector)
            err = float(np.linalg.norm(e))
            if err < tol:
                return q, True, err
            J = self.camera_jacobian(q)
            dq = J.T @ np.linalg.solve(J @ J.T + damping ** 2 * np.eye(6), e)
            n = np.linalg.norm(dq)
            if n > 0.5:  # keep steps small where the linearisation is poor
                dq *= 0.5 / n
            q = np.clip(pin.integrate(self.model, q, dq), self.lower, self.upper)
        return q, False, err

    def ik_for_cMo(self, cMo_des: pin.SE3, q_seed=None, **kw):
        """:meth:`solve_ik` for a desired target pose in the camera, ``cMo``."""
        return self.solve_ik(self.wMo * cMo_des.inverse(), q_seed, **kw)

    def move_to_camera_pose(self, wMc_des: pin.SE3, q_seed=None, **kw) -> tuple[bool, float]:
        """Jump to the IK solution for ``wMc_des`` if it converges; returns (ok, error)."""
        q, ok, err = self.solve_ik(wMc_des, q_seed, **kw)
        if ok:
            self.set_q(q)
        return ok, err
