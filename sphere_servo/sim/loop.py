"""Headless kinematic closed loop (no ROS, no arm): a free-flying camera servoed on a target.

The target frame o is the world frame. Each iteration: observe the target from ``cMo``
(exact projection by default, or any ``observer(cMo) -> Observation`` such as render +
detect), compute ``v_c`` with the :class:`~sphere_servo.core.control.Controller`, and move
the camera by the exact exponential map ``oMc ← oMc · exp6(v_c dt)``.

The returned :class:`LoopResult` holds the time histories needed for the paper's figures:
features, errors, twists, camera poses in the target and desired frames, and the image
trajectories of b and the marks.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import pinocchio as pin

from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.control import AdaptiveGain, Controller
from sphere_servo.core.features import make_feature_set
from sphere_servo.core.geometry import GeometryError, integrate_camera
from sphere_servo.core.measurement import Observation, observe
from sphere_servo.core.targets import Target

Observer = Callable[[pin.SE3], Observation]


@dataclass
class LoopResult:
    """Time histories of one run (N iterations; arrays indexed by iteration).

    t (N,) s; s, e (N, n) features and errors; v (N, 6) twists (camera frame);
    oMc (N+1, 4, 4) camera poses in the target frame (incl. the final one);
    b (N, 3) and q[name] (N, 3) unit vectors in the camera frame; in_view (N,) bool.
    """

    feature_set: str
    converged: bool
    reason: str
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
        """(translation error m, rotation error deg) of the last pose w.r.t. the desired."""
        cdMc = pin.SE3(self.oMc_desired).inverse() * pin.SE3(self.oMc[-1])
        return (float(np.linalg.norm(cdMc.translation)),
                float(np.degrees(np.linalg.norm(pin.log3(cdMc.rotation)))))

    def pose_error_vectors(self, last: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``(cdtc (K, 3) m, θu (K, 3) rad)``: pose of each recorded camera w.r.t. the
        desired one, in the desired camera frame, for the ``last`` K poses (default all)."""
        cdMo = pin.SE3(self.oMc_desired).inverse()
        poses = self.oMc if last is None else self.oMc[-last:]
        M = [cdMo * pin.SE3(oMc) for oMc in poses]
        return (np.array([m.translation for m in M]).reshape(-1, 3),
                np.array([pin.log3(m.rotation) for m in M]).reshape(-1, 3))


def run_loop(target: Target, cMo_start: pin.SE3, cMo_desired: pin.SE3,
             feature_set: str = 's_n', r_hat: float | None = None,
             gain: float | AdaptiveGain = 0.5, interaction: str = 'current',
             dt: float = 0.1, max_iter: int = 2000, tol: float = 1e-4,
             v_max: float = np.inf, w_max: float = np.inf,
             observer: Observer | None = None,
             camera: CameraIntrinsics | None = None, max_lost: int = 0,
             desired: Observation | None = None) -> LoopResult:
    """Servo a free-flying camera from ``cMo_start`` to ``cMo_desired``.

    feature_set  's_n', 's' or 's_cc'; r_hat defaults to the true radius.
    observer     ``cMo -> Observation``; defaults to the exact projection ``observe``.
    camera       if given, ``in_view`` records whether the sphere's centre direction and the
                 marks project inside the image (for visibility statistics).
    desired      the observation s* is computed from (default ``observer(cMo_desired)``);
                 give a noise-free one to teach from an averaged image under a noisy observer.
    max_lost     consecutive failed observations tolerated: the camera holds still (zero
                 twist, as the ``servo`` node does while the target is lost) and the
                 iteration is not recorded; one more and the run stops. Only useful with a
                 noisy observer — an exact one fails the same way again.
    Stops when ‖s − s*‖₂ < tol (converged), after ``max_iter`` iterations, or when the
    target can no longer be observed (reason says why).
    """
    observer = observer or (lambda cMo: observe(cMo, target))
    r_hat = target.radius if r_hat is None else r_hat
    fs = make_feature_set(feature_set, desired or observer(cMo_desired))
    ctrl = Controller(fs, r_hat, gain=gain, interaction=interaction, v_max=v_max,
                      w_max=w_max, tol=tol)
    oMc = cMo_start.inverse()
    poses, S, E, V, B, t = [oMc.homogeneous.copy()], [], [], [], [], []
    Q: dict[str, list] = {}
    in_view = []
    converged, reason = False, 'max_iter'
    lost = 0
    for k in range(max_iter):
        cMo = oMc.inverse()
        try:
            obs = observer(cMo)
            out = ctrl.compute(obs)
        except GeometryError as exc:  # MeasurementError, ControlError
            lost += 1
            if lost > max_lost:
                reason = f'target lost: {exc}'
                break
            continue
        lost = 0
        S.append(fs.features(obs))
        E.append(out.error)
        B.append(obs.sphere.b)
        for name, q in obs.q.items():
            Q.setdefault(name, []).append(q)
        if camera is not None:
            rays = np.array([obs.sphere.b, *obs.q.values()])
            in_view.append(bool(np.all(camera.in_image(camera.project(rays)))))
        t.append(k * dt)
        if out.converged:
            V.append(np.zeros(6))
            converged, reason = True, 'converged'
            break
        V.append(out.v_c)
        oMc = integrate_camera(oMc, out.v_c, dt)
        poses.append(oMc.homogeneous.copy())
    n = len(E)
    return LoopResult(
        feature_set=feature_set, converged=converged, reason=reason, iterations=n,
        t=np.array(t), s=np.array(S).reshape(n, fs.size), e=np.array(E).reshape(n, fs.size),
        v=np.array(V).reshape(n, 6), oMc=np.array(poses), b=np.array(B).reshape(n, 3),
        q={k: np.array(v) for k, v in Q.items()},
        in_view=np.array(in_view) if camera is not None else None,
        oMc_desired=cMo_desired.inverse().homogeneous.copy())
