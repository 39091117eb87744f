"""
``make demo``: the paper's special-sphere scenario (§IV.A.1) on the simulated UR5, over ROS 2.

Four processes (arm_sim, detector, features, servo) started by the launcher, in
lockstep. The arm shows the desired pose, its image is taught, the arm jumps to the start
pose and the servo brings it back with ``s_n``, with only the image in the loop.

Prints progress (iteration, ‖s − s*‖) as it goes and writes into ``runs/<timestamp>/``:
Fig. 3 (s_n error, camera velocities), Fig. 4 (camera trajectory from the ground truth,
image trajectories of b, P1, P2 from the detector), the run's rosbag2 (``bag/``, with
``arm_sim/markers``: the 3-D scene for Foxglove), and, made from that bag, the video
``servo.mp4`` (+ ``servo.gif``, :mod:`~sphere_servo.experiments.video`) and the 3-D replay
page ``replay.html`` (:mod:`~sphere_servo.experiments.replay3d`). Ends by printing where the
files are. Exit code 0 only if the servo converged and every file was written.

``--headless`` runs the kinematic loop instead (no ROS): the special sphere with s_n and the
CC target with s_cc, s_n and s.
"""
from __future__ import annotations

import argparse
from pathlib import Path
import sys
import time

import numpy as np
import pinocchio as pin

from sphere_servo.bringup import launcher
from sphere_servo.core.features import make_feature_set
from sphere_servo.core.measurement import observe
from sphere_servo.core.targets import cc_target, special_sphere
from sphere_servo.experiments.scenarios import CMO_DESIRED, CMO_FAR_START
from sphere_servo.pipeline.config import ConfigError, scenario
from sphere_servo.ros.vectors import FEATURE_NAMES
from sphere_servo.sim.loop import run_loop
from sphere_servo.sim.plots import fig3, fig4, Trajectory


def progress(res, every: int = 25) -> None:
    norms = np.linalg.norm(res.e, axis=1)
    for k in range(0, res.iterations, every):
        print(f'  [{res.feature_set:>4}] iteration {k:4d}  t={res.t[k]:6.2f} s  '
              f'‖s − s*‖ = {norms[k]:.3e}')
    dt_err, dr_err = res.final_pose_error()
    print(f'  [{res.feature_set:>4}] {res.reason} after {res.iterations} iterations; final '
          f'error {dt_err * 1000:.3f} mm, {dr_err:.4f}°; camera path {res.path_length:.3f} m '
          f'(straight {res.straight_distance:.3f} m)')


def headless(out: Path, gain: float, dt: float) -> tuple[bool, list]:
    ok = True
    print('§IV.A.1 special sphere, s_n (headless kinematic loop)')
    sp = special_sphere()
    res = run_loop(sp, CMO_FAR_START, CMO_DESIRED, 's_n', gain=gain, dt=dt)
    progress(res)
    ok &= res.converged
    labels = make_feature_set('s_n', observe(CMO_DESIRED, sp)).labels
    files = [fig3(res.t, res.e, res.v, labels, out / 'fig3_special_sn.png',
                  'Special sphere, s_n'),
             fig4({'s_n': res}, out / 'fig4_special_sn.png', 'Special sphere, s_n')]
    print('§IV.A.2 CC target: s_cc, s_n, s')
    runs = {}
    for name in ('s_cc', 's_n', 's'):
        runs[name] = run_loop(cc_target(), CMO_FAR_START, CMO_DESIRED, name, gain=gain, dt=dt)
        progress(runs[name])
        ok &= runs[name].converged
    files.append(fig4(runs, out / 'fig4_cc_compare.png', 'CC target: s_cc, s_n, s'))
    return ok, files


def run_window(sup) -> dict:
    """
    Select what the figures show of a ROS run, from the launcher's supervisor's histories.

    That is the servo run from the first image the enabled servo answered at the start pose
    (``sup.t_enabled``, else the first image there, ``sup.t_start``) on. The teach sequence
    before it (the arm at the desired pose measured against an earlier teach, the jump to the
    start, the frames until the servo is enabled) is not part of the run. Camera positions
    are in the taught camera frame (the ground truth of the taught image; the last pose when
    nothing was taught), so the trajectory ends where the servo really stopped.

    Returns ``t`` (n,) s from the start, ``e`` (n, 6) s − s*, ``v`` (n, 6) the twist sent for
    each features message (zero if none), ``cd_p`` (m, 3) camera centres in the taught frame,
    ``b`` (k, 3) and ``marks`` {name: (k, 3)} unit rays of the detected sphere centre and
    marks (camera frame), and ``iterations``: the servo's count of its iterations up to the
    first it called converged (None if it did not; the run goes on after that while the
    launcher stops the nodes, so the histories' length depends on timing, not this count).
    """
    t_start = sup.t_enabled if sup.t_enabled is not None else sup.t_start

    def run(history):  # by stamp: under load some messages are delivered late
        return sorted((h for h in history if h[0] >= t_start), key=lambda h: h[0])
    feats = run(sup.features)
    poses = run(sup.poses)
    meas = [(t, m) for t, m in run(sup.measurements) if 'b_x' in m]
    tw = dict(sup.twists)  # twist by image stamp
    t0 = feats[0][0] if feats else t_start
    oMcd = sup.oMc_taught if sup.oMc_taught is not None else (
        pin.SE3(poses[-1][1]) if poses else pin.SE3.Identity())
    cdMo = oMcd.inverse()
    marks = {}
    for name in ('P1', 'P2', 'P3'):
        rows = [[m[f'{name}_qx'], m[f'{name}_qy'], m[f'{name}_qz']] for _, m in meas
                if f'{name}_qx' in m]
        if rows:
            marks[name] = np.array(rows)
    return {'t': np.array([f[0] - t0 for f in feats]),
            'e': np.array([f[1] - f[2] for f in feats]).reshape(-1, 6),
            'v': np.array([tw.get(f[0], np.zeros(6)) for f in feats]).reshape(-1, 6),
            'cd_p': np.array([cdMo.act(pin.SE3(M).translation) for _, M in poses]
                             ).reshape(-1, 3),
            'b': np.array([[m['b_x'], m['b_y'], m['b_z']] for _, m in meas]).reshape(-1, 3),
            'marks': marks,
            'iterations': sup.iterations_converged}


def ros_figures(sup, out: Path, title: str, feature_set: str = 's_n') -> list[Path]:
    """Fig. 3 and Fig. 4 of the run :func:`run_window` selects."""
    w = run_window(sup)
    files = []
    if len(w['t']):
        files.append(fig3(w['t'], w['e'], w['v'], FEATURE_NAMES[feature_set],
                          out / 'fig3.png', title))
    if len(w['cd_p']) and len(w['b']):
        files.append(fig4({feature_set: Trajectory(w['cd_p'], w['b'], w['marks'])},
                          out / 'fig4.png', title))
    return files


def watch_files(bag: Path, out: Path, scenario: str) -> list[Path]:
    """
    Write the video (+ GIF) and the replay page of the run recorded in ``bag`` into ``out``.

    Raises BagError, SceneError or OSError when one cannot be made.
    """
    from sphere_servo.bag.offline import load_settings
    from sphere_servo.bag.run import load_arm_params, read_run, run_scene
    from sphere_servo.experiments.replay3d import make_replay
    from sphere_servo.experiments.video import make_video
    settings = load_settings(scenario)
    run = read_run(bag, settings)
    vid = make_video(run, out / 'servo.mp4', gif=out / 'servo.gif',
                     target_kind=settings.features.target_kind)
    page, _ = make_replay(run, run_scene(run, load_arm_params(scenario)), out / 'replay.html')
    return [vid.path, vid.gif, page]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.strip().split('\n\n')[0])
    ap.add_argument('--out', default='runs', help='parent folder of the run folder')
    ap.add_argument('--config', '--scenario', dest='scenario', default='special_sphere',
                    help='launcher scenario (config/scenarios/<name>.yaml)')
    ap.add_argument('--timeout', type=float, default=None, help='wall seconds')
    ap.add_argument('--no-record', action='store_true', help='do not record a rosbag2')
    ap.add_argument('--headless', action='store_true', help='kinematic loop, no ROS')
    ap.add_argument('--gain', type=float, default=0.5, help='λ (headless)')
    ap.add_argument('--dt', type=float, default=0.1, help='control period (headless)')
    args = ap.parse_args(argv)
    out = (Path(args.out) / time.strftime('%Y%m%d-%H%M%S')).resolve()
    out.mkdir(parents=True, exist_ok=True)
    written = True
    if args.headless:
        ok, files = headless(out, args.gain, args.dt)
    else:
        try:
            sc = scenario(args.scenario)
        except ConfigError as exc:
            print(f'demo: {exc}', file=sys.stderr)
            return launcher.ExitCode.BAD_CONFIG
        print(f'demo: {args.scenario} over ROS 2 ({", ".join(sc.nodes)})')
        bag = None if args.no_record else str(out / 'bag')
        code, sup, _ = launcher.run(sc, until_converged=True, timeout=args.timeout,
                                    record=bag, collect=True)
        ok = code == launcher.ExitCode.OK
        fset = sc.node_params('servo').get('feature_set', 's_n')
        files = ros_figures(sup, out, f'{args.scenario}: {fset} over ROS 2', fset)
        if bag and Path(bag).exists():
            files.append(Path(bag))
            try:
                files += watch_files(Path(bag), out, args.scenario)
            except (ValueError, OSError, ConfigError) as exc:  # BagError, SceneError, ...
                print(f'demo: error: no video or replay page: {" ".join(str(exc).split())}',
                      file=sys.stderr)
                written = False
    print('\nwrote:')
    for f in files:
        size = sum(p.stat().st_size for p in f.rglob('*')) if f.is_dir() else f.stat().st_size
        print(f'  {f} ({size / 1e6:.1f} MB)')
    print('converged' if ok else 'DID NOT CONVERGE')
    return 0 if ok and written else 1


if __name__ == '__main__':
    sys.exit(main())
