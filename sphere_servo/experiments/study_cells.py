"""
The cells of the Monte Carlo study: its conditions, start poses and one run (no ROS).

N random start poses of the camera around the CC target (0.3–0.7 m, on the marked side,
roll ±150°, sphere centre and both marks at least 20 px inside the 640×480 image, P1 seen
at most 80° from face-on so that a detector can find it). Sets: ``s_cc``, ``s_n``, ``s`` and
the point-based IBVS baseline (:mod:`~sphere_servo.experiments.ibvs`). Conditions:

=========  =================================================================  ===========
ideal      exact radius and intrinsics                                        exact obs.
rhat_0.5   r̂ = 0.5 r                                                           exact obs.
rhat_2     r̂ = 2 r                                                             exact obs.
calib      controller intrinsics +35 % px, +30 % py, −25 % u0, +27 % v0        exact obs.
noise      σ = 1 px Gaussian noise on 64 contour points and on the marks       exact obs.
images     rendered images (grey-level noise σ = 2) + the real detector       renderer+detector
balloon    ellipsoid 6 × 5.5 × 4.5 cm, r̂ = 6.5 cm (s_cc n/a: no tangent tip)  exact obs.
arm        ideal, with the UR5 in the loop (``arm_cell.run_arm``) and the       exact obs.
           robot cell's safety limit elbow ≤ 2.04 rad
           (``scenarios.JL_CELL_LIMITS``); starts the arm cannot reach inside
           its limits are left out
fisheye    ideal, seen by the equidistant fisheye of config/params/fisheye.yaml  exact obs.
catadiop.  ideal, seen by the unified ξ = 0.9 camera of catadioptric.yaml     exact obs.
*_wide     pinhole_wide, fisheye_wide, catadioptric_wide: ideal, each camera  exact obs.
           from the same *wide* starts (below)
=========  =================================================================  ===========

The camera conditions (issue 18) compare the cameras from the same starts: ``fisheye`` and
``catadioptric`` from the pinhole's starts (does the target still leave the image?), the
``*_wide`` ones from starts drawn for the wide cameras: the camera turned away from the
sphere by up to :data:`WIDE_TURN_DEG` about an axis across its optical axis, the sphere
centre and both marks at least 20 px inside the images of both wide cameras. A start whose
target is not in a camera's image (the pinhole's, for most wide starts) is a failure
"not in view at the start", without a run. The features are on the projection sphere, so
with exact intrinsics the observation is the same through every camera; what the camera
changes is what it sees: the start and the target leaving the image during the run.

"exact obs." is the analytic image (``sim/observers.exact_observer``): same geometry as the
detector's output, ~20× faster; ``images`` runs the first ``--n-images`` starts only.
Free-flying camera, dt = 0.1 s, ViSP adaptive gain, at most 400 iterations. A lost
observation is held through with zero twist for up to 5 frames (as the ``servo`` node
does); a sixth in a row ends the run as "target lost".

A run succeeds when ‖s − s*‖ falls under the tolerance (1e-4; 1e-3 for detected images),
the final pose is within 5 mm / 1° of the desired one, and the sphere centre and both
marks stayed in the image all along. Under ``noise`` ‖s − s*‖ never settles under a
tolerance, so those runs go 300 iterations and succeed when the camera's *mean* pose over
the last 50 is within 5 mm / 1° of the desired one; their "iterations" is the first at
which the camera came within 1 cm / 2° (and their path is measured up to there), and the
report adds the steady-state scatter. The noisy conditions teach s* from a noise-free image
(as averaging frames would), so the steady state measures the loop rather than one unlucky
desired frame.

A run's row is a JSON-able dict; its ``reason`` starts with the run's
:class:`~sphere_servo.sim.plants.LoopOutcome` value (the study's files keep the text).
"""
from __future__ import annotations

import functools
import time

import numpy as np
import pinocchio as pin

from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.central import CentralCamera
from sphere_servo.core.geometry import GeometryError
from sphere_servo.core.measurement import observe
from sphere_servo.core.targets import balloon, cc_target
from sphere_servo.experiments.arm_cell import arm_start, make_arm, run_arm
from sphere_servo.experiments.ibvs import IbvsFeatures
from sphere_servo.experiments.scenarios import (ADAPTIVE, CALIB_ERROR, camera_at, CMO_DESIRED,
                                                DT, IMAGE_TOL, JL_CELL_LIMITS)
from sphere_servo.pipeline.config import scenario
from sphere_servo.pipeline.params import ArmSimParams
from sphere_servo.sim.loop import LoopResult, run_loop
from sphere_servo.sim.observers import exact_observer, image_observer
from sphere_servo.sim.plants import LoopOutcome

SETS = ('s_cc', 's_n', 's', 'ibvs')
#: what the loop is given for each set: a name it knows, or the baseline's class
SET_SPECS = {'ibvs': IbvsFeatures}
CONDITIONS = ('ideal', 'rhat_0.5', 'rhat_2', 'calib', 'noise', 'images', 'balloon', 'arm',
              'fisheye', 'catadioptric', 'pinhole_wide', 'fisheye_wide', 'catadioptric_wide')
#: condition → the camera it is seen by (the others: the pinhole CAM)
CAMERA_OF = {'fisheye': 'fisheye', 'catadioptric': 'catadioptric', 'pinhole_wide': 'pinhole',
             'fisheye_wide': 'fisheye', 'catadioptric_wide': 'catadioptric'}
WIDE = ('pinhole_wide', 'fisheye_wide', 'catadioptric_wide')   # from the wide starts
WIDE_TURN_DEG = 100.0      # the wide starts' camera turned away from the sphere up to this
MAX_ITER = 400
MAX_MARK_ANGLE_DEG = 80.0  # P1 at most this far from face-on at the start
NOISY = ('noise',)  # judged on its steady state (see settle_stats)
NOISY_ITER = 300
SETTLE_WINDOW = 50
MAX_LOST = 5  # consecutive lost frames held through with zero twist, as the servo node does
CAM = CameraIntrinsics()
_CAMERAS = {}


def camera(name: str) -> CentralCamera:
    """Return the study's camera ``name``: 'pinhole' (CAM) or a wide config's arm_sim camera."""
    if name == 'pinhole':
        return CAM
    if name not in _CAMERAS:
        _CAMERAS[name] = ArmSimParams.from_mapping(scenario(name).node_params('arm_sim')).camera()
    return _CAMERAS[name]


def start_poses(n: int, seed: int = 0, margin_px: float = 20.0,
                max_mark_angle_deg: float = MAX_MARK_ANGLE_DEG, cameras=(CAM,),
                turn_deg: float = 0.0) -> list:
    """
    Draw ``n`` random ``cMo`` with the CC target's sphere centre and marks in the image.

    In the image of each of ``cameras``, ``margin_px`` inside. The camera aimed at the
    sphere, then (``turn_deg`` > 0) turned away from it by an angle uniform in
    ``[0, turn_deg]`` about a random axis across its optical axis. The surface mark P1 is
    seen at most ``max_mark_angle_deg`` from face-on: a mark closer to the limb is a sliver
    of a few pixels that no detector finds, so such a start tests the sampler rather than
    the servo.
    """
    rng = np.random.default_rng(seed)
    target = cc_target()
    oP1, cos_max = target.marks()['P1'], np.cos(np.radians(max_mark_angle_deg))
    poses = []
    while len(poses) < n:
        d = rng.uniform(0.3, 0.7)
        u = rng.normal(size=3)
        u[2] = -abs(u[2]) - 0.7  # the marked cap faces −z
        cMo = camera_at(d * u / np.linalg.norm(u), rng.uniform(-150, 150),
                        rng.normal(size=3) * 0.02)
        if turn_deg > 0:
            a = rng.uniform(0.0, 2.0 * np.pi)
            turn = np.radians(rng.uniform(0.0, turn_deg))
            cMo = pin.SE3(pin.exp3(turn * np.array([np.cos(a), np.sin(a), 0.0])),
                          np.zeros(3)) * cMo
        try:
            obs = observe(cMo, target, max_angle=min(c.max_angle for c in cameras))
        except GeometryError:
            continue
        rays = np.array([obs.sphere.b, *obs.q.values()])
        cP1 = cMo.act(oP1)
        n_c = cMo.rotation @ target.surface_normal(oP1)
        if (all(np.all(c.in_view(rays, margin=margin_px)) for c in cameras)
                and -(n_c @ cP1) / np.linalg.norm(cP1) >= cos_max):
            poses.append(cMo)
    return poses


def wide_start_poses(n: int, seed: int = 0) -> list:
    """Draw the wide starts: in both wide cameras' images, turned up to WIDE_TURN_DEG."""
    return start_poses(n, seed + 1, cameras=(camera('fisheye'), camera('catadioptric')),
                       turn_deg=WIDE_TURN_DEG)


def run_cell(task: tuple) -> dict:
    """Run one cell: ``(condition, set, index, cMo homogeneous)`` → a JSON-able row."""
    cond, fs, idx, M = task
    cMo = pin.SE3(np.asarray(M))
    target = balloon() if cond == 'balloon' else cc_target()
    ctrl_cam = CAM.with_error(**CALIB_ERROR) if cond == 'calib' else CAM
    r_hat = {'rhat_0.5': 0.5 * target.radius, 'rhat_2': 2.0 * target.radius,
             'balloon': 0.065}.get(cond, target.radius)
    noisy = cond in NOISY
    # noisy conditions teach s* from a noise-free image (as an average of frames would):
    # the steady-state error then measures the loop, not one unlucky desired frame
    desired = None
    if cond == 'images':
        obs = image_observer(target, CAM, noise_sigma=2.0, seed=idx)
        desired = image_observer(target, CAM)(CMO_DESIRED)
    elif cond == 'noise':
        obs = exact_observer(target, CAM, pixel_noise=1.0, seed=idx)
        desired = exact_observer(target, CAM)(CMO_DESIRED)
    elif cond in CAMERA_OF:
        ctrl_cam = camera(CAMERA_OF[cond])
        obs = functools.partial(observe, target=target, max_angle=ctrl_cam.max_angle)
    else:
        obs = exact_observer(target, CAM, None if ctrl_cam is CAM else ctrl_cam)
    t0 = time.perf_counter()
    if cond == 'arm':
        return _run_arm_cell(cond, fs, idx, cMo, target, t0)
    if cond in CAMERA_OF:
        try:
            seen = observe(cMo, target, max_angle=ctrl_cam.max_angle)
            rays = np.array([seen.sphere.b, *seen.q.values()])
            in_view = bool(np.all(ctrl_cam.in_view(rays)))
        except GeometryError:
            in_view = False
        if not in_view:
            return _lost_at_start(cond, fs, idx, NOT_IN_VIEW, t0)
    try:
        obs(cMo)  # run_loop cannot report a failure of the very first observation
        # with noise ‖s − s*‖ never settles under a tolerance: run the whole horizon and
        # judge the camera's pose over its last SETTLE_WINDOW iterations instead
        res = run_loop(target, cMo, CMO_DESIRED, SET_SPECS.get(fs, fs), r_hat=r_hat,
                       gain=ADAPTIVE, dt=DT, max_iter=NOISY_ITER if noisy else MAX_ITER,
                       tol=1e-12 if noisy else IMAGE_TOL if cond == 'images' else 1e-4,
                       observer=obs, camera=ctrl_cam, max_lost=MAX_LOST, desired=desired)
    except GeometryError as exc:  # the target is not observable from this start
        return _lost_at_start(cond, fs, idx, exc, t0)
    left = bool(res.in_view is not None and not np.all(res.in_view))
    row = {'cond': cond, 'set': fs, 'idx': idx, 'left_image': left,
           'iterations': res.iterations, 'path': res.path_length,
           'straight': res.straight_distance}
    et, er = res.final_pose_error()
    row.update(final_t_mm=et * 1e3, final_r_deg=er)
    if noisy and res.outcome is LoopOutcome.MAX_ITER:
        row.update(settle_stats(res))
        conv = row['bias_mm'] < 5.0 and row['bias_deg'] < 1.0
        why = res.reason if conv else ('did not settle on the desired pose (mean error '
                                       f"{row['bias_mm']:.0f} mm / {row['bias_deg']:.1f}°)")
    else:
        conv = bool(res.converged and et < 0.005 and er < 1.0)
        why = res.reason if conv or res.outcome is LoopOutcome.TARGET_LOST else (
            f'{res.reason} (‖e‖={np.linalg.norm(res.e[-1]):.2g})' if not res.converged
            else f'converged away from the desired pose ({et * 1e3:.0f} mm / {er:.1f}°)')
    row.update(converged=bool(conv), success=bool(conv and not left), reason=why,
               seconds=time.perf_counter() - t0)
    return row


#: the cause of a camera condition's start whose target is not in the camera's image
NOT_IN_VIEW = 'not in view at the start'


def _lost_at_start(cond: str, fs: str, idx: int, exc: Exception | str, t0: float) -> dict:
    """Return the row of a run whose target is not observable from its start."""
    return {'cond': cond, 'set': fs, 'idx': idx, 'success': False, 'converged': False,
            'reason': exc if exc == NOT_IN_VIEW else
            f'{LoopOutcome.TARGET_LOST.value} at the start: {exc}',
            'left_image': False, 'iterations': 0, 'path': 0.0, 'straight': 1.0,
            'seconds': time.perf_counter() - t0}


def _arm_reason(res: LoopResult) -> str:
    """Return an arm run's reason for its row: at a joint limit, the joints that met it."""
    if res.outcome is LoopOutcome.JOINT_LIMIT:
        return f'{res.outcome.value}: {", ".join(res.limit_joints)}'
    return res.reason


_ARM = {}


def _run_arm_cell(cond, fs, idx, cMo, target, t0) -> dict:
    """Run the ``arm`` condition: :func:`arm_cell.run_arm` with the cell's safety limit."""
    if 'arm' not in _ARM:  # one UR5 model per worker process
        _ARM['arm'] = make_arm(JL_CELL_LIMITS)
    arm = _ARM['arm']
    try:
        arm_start(arm, cMo, CMO_DESIRED)
    except GeometryError as exc:
        return {'cond': cond, 'set': fs, 'idx': idx, 'excluded': f'start unreachable: {exc}',
                'success': False, 'converged': False, 'reason': 'excluded',
                'left_image': False, 'iterations': 0, 'path': 0.0, 'straight': 1.0,
                'seconds': time.perf_counter() - t0}
    try:
        res = run_arm(target, cMo, CMO_DESIRED, SET_SPECS.get(fs, fs), gain=ADAPTIVE,
                      max_iter=MAX_ITER, arm=arm, camera=CAM)
    except GeometryError as exc:  # the target is not observable from this start
        return _lost_at_start(cond, fs, idx, exc, t0)
    et, er = res.final_pose_error()
    left = bool(not np.all(res.in_view))
    conv = bool(res.converged and et < 0.005 and er < 1.0)
    return {'cond': cond, 'set': fs, 'idx': idx, 'converged': conv,
            'success': bool(conv and not left), 'left_image': left,
            'joint_limit': res.outcome is LoopOutcome.JOINT_LIMIT, 'reason': _arm_reason(res),
            'iterations': res.iterations, 'path': res.path_length,
            'straight': res.straight_distance, 'final_t_mm': et * 1e3, 'final_r_deg': er,
            'seconds': time.perf_counter() - t0}


def settle_stats(res: LoopResult) -> dict:
    """
    Measure the steady state of a noisy run over its last ``SETTLE_WINDOW`` poses.

    Returns the mean pose error (bias, mm / deg), the RMS scatter about it (jitter) and the
    first iteration at which the camera came within 1 cm / 2° of the desired pose (its path
    is measured up to there).
    """
    t, w = res.pose_error_vectors(SETTLE_WINDOW)
    t_all, w_all = res.pose_error_vectors()
    inside = (np.linalg.norm(t_all, axis=1) < 0.01) & (
        np.degrees(np.linalg.norm(w_all, axis=1)) < 2.0)
    k = int(np.argmax(inside)) if inside.any() else res.iterations
    # the path up to that arrival: after it the camera only jitters about the goal
    path = float(np.sum(np.linalg.norm(np.diff(res.positions[:k + 1], axis=0), axis=1)))
    dt, dw = t - t.mean(0), w - w.mean(0)
    return {'path': path, 'bias_mm': 1e3 * float(np.linalg.norm(t.mean(0))),
            'bias_deg': float(np.degrees(np.linalg.norm(w.mean(0)))),
            'jitter_mm': 1e3 * float(np.sqrt(np.mean(np.sum(dt ** 2, 1)))),
            'jitter_deg': float(np.degrees(np.sqrt(np.mean(np.sum(dw ** 2, 1))))),
            'iterations': k}


def tasks(n: int, n_images: int, seed: int) -> list:
    """List the study's cells: ``(condition, set, start index, cMo homogeneous)``."""
    poses = start_poses(n, seed)
    wide = wide_start_poses(n, seed)
    out = []
    for cond in CONDITIONS:
        starts = wide if cond in WIDE else poses
        for idx, cMo in enumerate(starts[:n_images] if cond == 'images' else starts):
            for fs in SETS:
                if cond == 'balloon' and fs == 's_cc':
                    continue
                out.append((cond, fs, idx, cMo.homogeneous.tolist()))
    return out
