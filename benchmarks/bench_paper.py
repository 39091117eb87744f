"""
Benchmark of the Monte Carlo study (issue 7) and of the headless loop beside a peer's IBVS.

Time per study run (exact observation and rendered images + detector), the projected wall
time of ``make study`` at N = 500 on 2 workers (target < 30 min), and — when it can be
installed — machinevision-toolbox-python's ``IBVS`` class stepping a comparable simulation,
time per iteration, beside our loop's.

The peer lives in its own virtual environment (``.venv-mvtb``, created here if missing:
it pulls a full OpenCV that clashes with the headless one) and runs as a subprocess. If it
cannot be installed (no network, build failure), its row says so and the rest still runs.
"""
from __future__ import annotations

import json
from pathlib import Path
import subprocess
import sys
import time

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
MVTB_VENV = ROOT / '.venv-mvtb'
PEER = r"""
import json, time, numpy as np
from spatialmath import SE3
from machinevisiontoolbox import CentralCamera
try:
    from machinevisiontoolbox import IBVS
except ImportError:
    from machinevisiontoolbox.VisualServo import IBVS
cam = CentralCamera.Default(pose=SE3.Trans(0.05, -0.03, -0.6) * SE3.Rz(0.6))
P = np.array([[0.0, 0.0, 0.0], [0.0, 0.025, -0.043], [0.025, 0.0, -0.043]]).T
pd = CentralCamera.Default(pose=SE3.Trans(0, 0, -0.45)).project_point(P)
ibvs = IBVS(cam, P=P, p_d=pd, graphics=False, depth=0.45)
n = 200
t0 = time.perf_counter()
ibvs.run(n)
print(json.dumps({"us_per_step": (time.perf_counter() - t0) / n * 1e6}))
"""


def _median_s(fn, n: int) -> float:
    ts = []
    for _ in range(n):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts))


def _peer_us(log=sys.stdout) -> tuple[float | None, str]:
    py = MVTB_VENV / 'bin' / 'python'
    try:
        if not py.exists():
            log.write('[bench_paper] creating .venv-mvtb (pip install '
                      'machinevision-toolbox-python) …\n')
            subprocess.run([sys.executable, '-m', 'venv', str(MVTB_VENV)], check=True,
                           capture_output=True, timeout=300)
            subprocess.run([str(py), '-m', 'pip', 'install', '-q',
                            'machinevision-toolbox-python'], check=True,
                           capture_output=True, timeout=1200)
        out = subprocess.run([str(py), '-c', PEER], check=True, capture_output=True,
                             text=True, timeout=600)
        return float(json.loads(out.stdout.strip().splitlines()[-1])['us_per_step']), ''
    except (subprocess.SubprocessError, OSError, ValueError, KeyError) as exc:
        err = getattr(exc, 'stderr', '') or str(exc)
        err = err.decode() if isinstance(err, bytes) else err
        return None, (err.strip().splitlines() or ['failed'])[-1][:120]


def run(quick: bool = False) -> list[dict]:
    from sphere_servo.core.targets import cc_target
    from sphere_servo.experiments import study_cells as study
    from sphere_servo.experiments.ibvs import IbvsFeatures
    from sphere_servo.experiments.scenarios import CMO_DESIRED
    from sphere_servo.sim.loop import run_loop
    k = 4 if quick else 12
    poses = study.start_poses(k, seed=1)
    cells = {c: [(c, fs, i, p.homogeneous.tolist()) for i, p in enumerate(poses)
                 for fs in study.SETS] for c in ('ideal', 'noise', 'images')}
    per = {}
    for c, ts in cells.items():
        sub = ts[:4] if c == 'images' else ts
        t0 = time.perf_counter()
        for t in sub:
            study.run_cell(t)
        per[c] = (time.perf_counter() - t0) / len(sub)
    n_img = 50
    runs = {c: 500 * (3 if c == 'balloon' else 4) for c in study.CONDITIONS}
    runs['images'] = n_img * 4
    cpu = sum(runs[c] * per['images' if c == 'images' else 'noise' if c == 'noise'
                            else 'ideal'] for c in runs)
    projected_min = cpu / 2 / 60
    # our loop's time per iteration (s_n, exact observation) vs the peer's IBVS step
    tgt = cc_target()
    t_loop = _median_s(lambda: run_loop(tgt, poses[0], CMO_DESIRED, IbvsFeatures, max_iter=100,
                                        tol=1e-12), 3) / 100 * 1e6
    peer, why = _peer_us()
    rows = [
        {'name': 'study: one run, exact observation (ideal)', 'value': per['ideal'] * 1e3,
         'unit': 'ms', 'baseline': None, 'baseline_name': None, 'ratio': None,
         'target': ''},
        {'name': 'study: one run, rendered images + detector', 'value': per['images'] * 1e3,
         'unit': 'ms', 'baseline': per['ideal'] * 1e3, 'baseline_name': 'exact observation',
         'ratio': per['images'] / per['ideal'], 'target': ''},
        {'name': 'study: N=500 projected wall time, 2 workers', 'value': projected_min,
         'unit': 'min', 'baseline': 30.0, 'baseline_name': 'target', 'ratio':
         projected_min / 30.0, 'target': '< 30 min'},
        {'name': 'headless loop: IBVS iteration (exact obs.)', 'value': t_loop, 'unit': 'µs',
         'baseline': peer, 'baseline_name': 'mvtb IBVS.step' if peer else
         f'mvtb IBVS unavailable: {why}', 'ratio': t_loop / peer if peer else None,
         'target': ''}]
    return rows


if __name__ == '__main__':
    for row in run(quick='--quick' in sys.argv):
        print(row)
