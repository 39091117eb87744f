"""
The headless closed loop (no ROS): observe → control law → plant step, until it ends.

The target frame o is the world frame. Each iteration observes the target from the plant's
``cMo`` (exact projection by default, or any ``observer(cMo) -> Observation`` such as render
+ detect), computes ``v_c`` with the :class:`~sphere_servo.core.control.Controller` (paper
eq. 17) and hands it to the plant (:mod:`sphere_servo.sim.plants`: a free-flying camera
moved by the exact exponential map ``oMc ← oMc · exp6(v_c dt)``, or the UR5 arm).
:func:`closed_loop` runs any plant; :func:`run_loop` is the free-flying camera.

The returned :class:`LoopResult` holds the time histories needed for the paper's figures:
features, errors, twists, camera poses in the target and desired frames, and the image
trajectories of b and the marks; why the run ended is a :class:`LoopOutcome`.
"""
from __future__ import annotations

from dataclasses import dataclass, field
import math
from typing import Callable, Protocol

import numpy as np
import pinocchio as pin

from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.control import AdaptiveGain, Controller
from sphere_servo.core.features import FeatureSet, make_feature_set
from sphere_servo.core.geometry import GeometryError
from sphere_servo.core.measurement import Observation, observe
from sphere_servo.core.targets import Target
from sphere_servo.sim.arm import Status
from sphere_servo.sim.plants import FreeCamera, JointLimits, LoopOutcome, PlantStop

Observer = Callable[[pin.SE3], Observation]
#: a feature set by name (``make_feature_set``) or by class (e.g. a baseline's)
FeatureSetSpec = str | type[FeatureSet]


class Plant(Protocol):
    """What the loop servos (see :mod:`sphere_servo.sim.plants`)."""

    def desired_cMo(self) -> pin.SE3:
        """Return the pose of the target in the camera at the desired pose."""

    def desired_oMc(self) -> np.ndarray:
        """Return the desired camera pose in the target frame (4, 4)."""

    def cMo(self) -> pin.SE3:
        """Return the pose of the target in the current camera."""

    def oMc(self) -> np.ndarray:
        """Return the current camera pose in the target frame (4, 4)."""

    def step(self, v_c: np.ndarray, dt: float) -> PlantStop | None:
        """Execute twist ``v_c`` for ``dt`` s; return a :class:`PlantStop` if the run ends."""

    def record(self) -> dict:
        """Return the fields of :class:`LoopResult` only this plant records."""


@dataclass
class LoopResult:
    """
    Time histories of one run (N iterations; arrays indexed by iteration).

    t (N,) s; s, e (N, n) features and errors; v (N, 6) twists (camera frame);
    oMc (N+1, 4, 4) camera poses in the target frame (incl. the final one; a lost frame
    held through records none); b (N, 3) and q[name] (N, 3) unit vectors in the camera
    frame; in_view (N,) bool (when a camera was given). ``outcome`` says why the run ended
    and ``detail`` how (the exception of a lost target, the arm's message at a limit).
    Arm runs also carry ``joints`` (N+1, nq) rad, ``arm_status`` (one
    :class:`~sphere_servo.sim.arm.Status` per arm step), ``joint_limits`` and, at a joint
    limit, the joints that met it (``limit_joints``).
    """

    feature_set: str
    outcome: LoopOutcome
    iterations: int
    t: np.ndarray
    s: np.ndarray
    e: np.ndarray
    v: np.ndarray
    oMc: np.ndarray
    b: np.ndarray
    q: dict = field(default_factory=dict)
    in_view: np.ndarray | None = None
    oMc_desired: np.ndarray | None = None
    detail: str = ''
    limit_joints: tuple[str, ...] = ()
    joints: np.ndarray | None = None
    arm_status: list[Status] | None = None
    joint_limits: JointLimits | None = None

    @property
    def converged(self) -> bool:
        """Whether ‖s − s*‖₂ fell under the tolerance."""
        return self.outcome is LoopOutcome.CONVERGED

    @property
    def reason(self) -> str:
        """Why the run ended, in words: the outcome, then its detail (for reports)."""
        return f'{self.outcome.value}: {self.detail}' if self.detail else self.outcome.value

    @property
    def positions(self) -> np.ndarray:
        """(N+1, 3) camera centre in the target frame."""
        return self.oMc[:, :3, 3]

    @property
    def path_length(self) -> float:
        """Length of the camera centre's path (m)."""
        return float(np.sum(np.linalg.norm(np.diff(self.positions, axis=0), axis=1)))

    @property
    def straight_distance(self) -> float:
        """Distance from the start position to the desired one (m)."""
        return float(np.linalg.norm(self.positions[0] - self.oMc_desired[:3, 3]))

    def final_pose_error(self) -> tuple[float, float]:
        """Return (translation error m, rotation error deg) of the last pose to the desired."""
        cdMc = pin.SE3(self.oMc_desired).inverse() * pin.SE3(self.oMc[-1])
        return (float(np.linalg.norm(cdMc.translation)),
                float(np.degrees(np.linalg.norm(pin.log3(cdMc.rotation)))))

    def pose_error_vectors(self, last: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """
        Pose of each recorded camera w.r.t. the desired one, in the desired camera frame.

        Returns ``(cdtc (K, 3) m, θu (K, 3) rad)`` for the ``last`` K poses (default all).
        """
        cdMo = pin.SE3(self.oMc_desired).inverse()
        poses = self.oMc if last is None else self.oMc[-last:]
        M = [cdMo * pin.SE3(oMc) for oMc in poses]
        return (np.array([m.translation for m in M]).reshape(-1, 3),
                np.array([pin.log3(m.rotation) for m in M]).reshape(-1, 3))


def closed_loop(plant: Plant, target: Target, feature_set: FeatureSetSpec = 's_n',
                r_hat: float | None = None, gain: float | AdaptiveGain = 0.5,
                interaction: str = 'current', dt: float = 0.1, max_iter: int = 2000,
                tol: float = 1e-4, v_max: float = np.inf, w_max: float = np.inf,
                observer: Observer | None = None, camera: CameraIntrinsics | None = None,
                max_lost: int = 0, desired: Observation | None = None) -> LoopResult:
    """
    Servo ``plant`` from where it is to its desired pose (the loop of every plant).

    feature_set  's_n', 's', 's_cc' (or a registered name), or a FeatureSet class.
    r_hat        defaults to the true radius.
    observer     ``cMo -> Observation``; defaults to the exact projection ``observe``.
    camera       if given, ``in_view`` records whether the sphere's centre direction and the
                 marks project inside the image (for visibility statistics).
    desired      the observation s* is computed from (default: the observer's at the
                 plant's desired pose); give a noise-free one to teach from an averaged
                 image under a noisy observer.
    max_lost     consecutive failed observations tolerated: the plant is not stepped (the
                 camera holds still, as the ``servo`` node's zero twist holds the arm) and
                 the iteration is not recorded; one more and the run stops. Only useful
                 with a noisy observer — an exact one fails the same way again.
    Stops when ‖s − s*‖₂ < tol (CONVERGED), after ``max_iter`` iterations (MAX_ITER), when
    the target can no longer be observed (TARGET_LOST), or where the plant stops it.
    ValueError, before anything runs, on a ``dt`` not finite and > 0 (0 ran ``max_iter``
    iterations of nothing; a negative one reversed every twist, and the run ended "target
    lost"), or a ``max_iter`` < 1 or ``max_lost`` < 0 that is not an integer.
    """
    if not (isinstance(dt, (int, float, np.floating, np.integer)) and math.isfinite(dt)
            and dt > 0):
        raise ValueError(f'dt must be a finite number of seconds > 0, got {dt!r}')
    for name, val, lo in (('max_iter', max_iter, 1), ('max_lost', max_lost, 0)):
        if isinstance(val, bool) or not isinstance(val, (int, np.integer)) or val < lo:
            raise ValueError(f'{name} must be an integer >= {lo}, got {val!r}')
    observer = observer or (lambda cMo: observe(cMo, target))
    r_hat = target.radius if r_hat is None else r_hat
    s_star = desired or observer(plant.desired_cMo())
    if isinstance(feature_set, str):
        name, fs = feature_set, make_feature_set(feature_set, s_star)
    else:
        name, fs = feature_set.name, feature_set(s_star)
    ctrl = Controller(fs, r_hat, gain=gain, interaction=interaction, v_max=v_max,
                      w_max=w_max, tol=tol)
    poses, S, E, V, B, t = [plant.oMc()], [], [], [], [], []
    Q: dict[str, list] = {}
    in_view = []
    outcome, detail, limit_joints = LoopOutcome.MAX_ITER, '', ()
    lost = 0
    for k in range(max_iter):
        try:
            obs = observer(plant.cMo())
            out = ctrl.compute(obs)
        except GeometryError as exc:  # MeasurementError, ControlError
            lost += 1
            if lost > max_lost:
                outcome, detail = LoopOutcome.TARGET_LOST, str(exc)
                break
            continue
        lost = 0
        S.append(fs.features(obs))
        E.append(out.error)
        B.append(obs.sphere.b)
        for mark, q in obs.q.items():
            Q.setdefault(mark, []).append(q)
        if camera is not None:
            rays = np.array([obs.sphere.b, *obs.q.values()])
            in_view.append(bool(np.all(camera.in_view(rays))))
        t.append(k * dt)
        if out.converged:
            V.append(np.zeros(6))
            outcome = LoopOutcome.CONVERGED
            break
        V.append(out.v_c)
        stop = plant.step(out.v_c, dt)
        poses.append(plant.oMc())
        if stop is not None:
            outcome, detail, limit_joints = stop.outcome, stop.detail, stop.joints
            break
    n = len(E)
    return LoopResult(
        feature_set=name, outcome=outcome, detail=detail, limit_joints=limit_joints,
        iterations=n, t=np.array(t), s=np.array(S).reshape(n, fs.size),
        e=np.array(E).reshape(n, fs.size), v=np.array(V).reshape(n, 6),
        oMc=np.array(poses), b=np.array(B).reshape(n, 3),
        q={k: np.array(v) for k, v in Q.items()},
        in_view=np.array(in_view) if camera is not None else None,
        oMc_desired=plant.desired_oMc(), **plant.record())


def run_loop(target: Target, cMo_start: pin.SE3, cMo_desired: pin.SE3,
             feature_set: FeatureSetSpec = 's_n', r_hat: float | None = None,
             gain: float | AdaptiveGain = 0.5, interaction: str = 'current',
             dt: float = 0.1, max_iter: int = 2000, tol: float = 1e-4,
             v_max: float = np.inf, w_max: float = np.inf,
             observer: Observer | None = None,
             camera: CameraIntrinsics | None = None, max_lost: int = 0,
             desired: Observation | None = None) -> LoopResult:
    """
    Servo a free-flying camera from ``cMo_start`` to ``cMo_desired``.

    The :func:`closed_loop` of a :class:`~sphere_servo.sim.plants.FreeCamera`; the
    arguments are :func:`closed_loop`'s.
    """
    return closed_loop(FreeCamera(cMo_start, cMo_desired), target, feature_set, r_hat=r_hat,
                       gain=gain, interaction=interaction, dt=dt, max_iter=max_iter,
                       tol=tol, v_max=v_max, w_max=w_max, observer=observer, camera=camera,
                       max_lost=max_lost, desired=desired)
