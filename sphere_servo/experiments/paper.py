"""
``make paper``: the paper's scenarios through the headless loop, their figures and a report.

    python -m sphere_servo.experiments.paper [--out DIR] [--quick] [--ros] [--search-joint-limit]

The scenarios (Tatsambon Fomena & Chaumette, §IV; the table is
:data:`~sphere_servo.experiments.scenarios.SCENARIOS`) run with rendered images and the
real detector: each renders the target with the *true* camera and detects it with the
*controller's* camera (which carries the calibration error when asked), then
``Detection.to_observation`` feeds the feature set: the vision pipeline is in the loop. Runs
are deterministic (noise-free renderer, fixed seeds). ``joint_limit`` puts the simulated UR5
in the loop (:func:`~sphere_servo.experiments.arm_cell.run_arm`).

Writes ``<out>/<timestamp>/``: one PNG per figure and ``report.md`` with a table whose
numbers come from this run (:mod:`~sphere_servo.experiments.paper_report`). ``--ros`` also
runs the key configs through the ROS 2 loop (``launcher.run``; slow). Python API:
:func:`run_scenario`, :func:`run_all`, :func:`run_ros`.
"""
from __future__ import annotations

import argparse
from dataclasses import dataclass, field
from pathlib import Path
import sys
import time

from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.experiments.arm_cell import run_arm, search_joint_limit_start
from sphere_servo.experiments.paper_report import figures, fmt, metrics, write_report
from sphere_servo.experiments.scenarios import (ADAPTIVE, CALIB_ERROR, CMO_DESIRED, DT,
                                                IMAGE_TOL, make_target, PAPER_GAIN, Scenario,
                                                SCENARIOS)
from sphere_servo.pipeline.config import scenario
from sphere_servo.sim.loop import run_loop
from sphere_servo.sim.observers import exact_observer, image_observer
from sphere_servo.sim.plots import shrink_png


@dataclass
class ScenarioResult:
    """The runs of one scenario: set name → ``LoopResult``, and how they were made."""

    scenario: Scenario
    runs: dict                       # set name → LoopResult
    camera: CameraIntrinsics         # controller's camera (projects observed rays to px)
    seconds: float = 0.0
    figures: list = field(default_factory=list)


def run_scenario(sc: Scenario | str, quick: bool = False, images: bool = True,
                 seed: int = 0) -> ScenarioResult:
    """
    Run every feature set of a scenario.

    Rendered images + detector unless ``images=False``; ``quick`` caps the iterations.
    """
    sc = SCENARIOS[sc] if isinstance(sc, str) else sc
    target = make_target(sc.target)
    cam = CameraIntrinsics()
    ctrl_cam = cam.with_error(**CALIB_ERROR) if sc.calib else cam
    r_hat = sc.r_hat_m or (target.radius * sc.r_hat if sc.r_hat else target.radius)
    gain = ADAPTIVE if sc.adaptive else PAPER_GAIN
    max_iter = min(sc.max_iter, 250) if quick else sc.max_iter
    tol = IMAGE_TOL if images else 1e-4
    t0 = time.perf_counter()
    runs = {}
    for fs in sc.sets:
        obs = (image_observer(target, cam, ctrl_cam, seed=seed) if images
               else exact_observer(target, cam, None if ctrl_cam is cam else ctrl_cam))
        kw = {'r_hat': r_hat, 'gain': gain, 'dt': DT, 'max_iter': max_iter, 'tol': tol,
              'observer': obs, 'camera': ctrl_cam}
        if sc.arm:
            runs[fs] = run_arm(target, sc.start, CMO_DESIRED, fs, turns=sc.turns,
                               cell_limits=sc.cell_limits, **kw)
        else:
            runs[fs] = run_loop(target, sc.start, CMO_DESIRED, fs, **kw)
    return ScenarioResult(sc, runs, ctrl_cam, time.perf_counter() - t0)


def run_all(names=None, quick: bool = False, images: bool = True, out=sys.stdout) -> list:
    """Run the named scenarios (all by default); print one line per run."""
    results = []
    for name in names or SCENARIOS:
        out.write(f'[paper] {name}: {SCENARIOS[name].title}\n')
        out.flush()
        r = run_scenario(name, quick=quick, images=images)
        for fs, res in r.runs.items():
            m = metrics(res, r.camera)
            out.write(f'  {fs:>4}: {res.reason} after {res.iterations} it, path '
                      f'{m["path_m"]:.3f} m (straight {m["straight_m"]:.3f}), final '
                      f'{m["final_t_mm"]:.2f} mm / {m["final_r_deg"]:.3f}°\n')
        out.write(f'  ({r.seconds:.1f} s)\n')
        results.append(r)
    return results


def run_ros(names, out: Path, log=sys.stdout) -> list[str]:
    """
    Run the key scenarios' configs through the ROS 2 loop (``launcher.run``).

    Figures via the demo's ``ros_figures``. Returns the report's lines.
    """
    from sphere_servo.bringup import launcher  # lazy: the ROS layers only for --ros
    from sphere_servo.experiments.demo import ros_figures
    lines = ['## Through the ROS 2 loop', '',
             'The same scenarios as four rclpy processes over DDS (`launcher --config <name> '
             '--until-converged`, lockstep): teach at the desired pose, jump to the start, '
             'servo on the detected image. Final error: last ground-truth camera pose against '
             'the taught one.', '',
             '| config | exit code | converged | iterations from the start | '
             'final error (mm) | final error (°) |', '|---|---|---|---|---|---|']
    figs_md = []
    for name in names:
        sc = SCENARIOS[name]
        if not sc.ros:
            continue
        cfg = scenario(sc.ros)
        code, sup, _ = launcher.run(cfg, until_converged=True, collect=True, out=log)
        sub = out / f'ros_{sc.ros}'
        sub.mkdir(exist_ok=True)
        fset = cfg.node_params('servo').get('feature_set', 's_n')
        figs = [] if sup is None else [
            shrink_png(f) for f in ros_figures(sup, sub, f'{sc.ros} over ROS 2', fset)]
        err = None if sup is None else sup.final_pose_error()
        iters = None if sup is None else sup.iterations_converged
        et, er = ('—', '—') if err is None else (f'{1e3 * err[0]:.2f}', f'{err[1]:.3f}')
        lines.append(f'| {sc.ros} | {int(code)} | '
                     f'{fmt(code == launcher.ExitCode.OK)} | '
                     f'{"—" if iters is None else iters} | '
                     f'{et} | {er} |')
        figs_md += [f'### {sc.ros}', ''] + [f'![{f.stem}]({sub.name}/{f.name})' for f in figs] \
            + ['']
    return lines + [''] + figs_md


def main(argv=None) -> int:
    """Run the paper's scenarios, write the figures and the report; 0 if they behaved."""
    ap = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    ap.add_argument('--out', default='runs/paper', help='parent folder of the run folder')
    ap.add_argument('--quick', action='store_true', help='fewer iterations')
    ap.add_argument('--exact', action='store_true', help='exact observation, no images')
    ap.add_argument('--ros', action='store_true', help='also run the key configs over ROS 2')
    ap.add_argument('--only', nargs='*', help=f'subset of {list(SCENARIOS)}')
    ap.add_argument('--search-joint-limit', type=int, metavar='N', default=0,
                    help='search N start poses for the joint-limit scenario and exit')
    args = ap.parse_args(argv)
    if args.search_joint_limit:
        found = search_joint_limit_start(args.search_joint_limit)
        print(f'{len(found)} candidate(s); best: {found[0] if found else None}')
        return 0 if found else 1
    out = (Path(args.out) / time.strftime('%Y%m%d-%H%M%S')).resolve()
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    results = run_all(args.only, quick=args.quick, images=not args.exact)
    for r in results:
        figures(r, out)
    report = write_report(results, out, time.perf_counter() - t0, args.quick)
    if args.ros:
        extra = run_ros(args.only or list(SCENARIOS), out)
        report.write_text(report.read_text() + '\n'.join(extra) + '\n')
    print(f'[paper] wrote {report}')
    ok = all(res.converged for r in results for fs, res in r.runs.items()
             if not (r.scenario.arm and fs == 's_cc'))
    return 0 if ok else 1


if __name__ == '__main__':
    sys.exit(main())
