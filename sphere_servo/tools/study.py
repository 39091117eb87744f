"""``make study``: Monte Carlo study of the feature sets over random start poses.

    python -m sphere_servo.tools.study [--n 500] [--n-images 50] [--out docs/study]
                                       [--resume] [--workers 2] [--seed 0]

N random start poses of the camera around the CC target (0.3–0.7 m, on the marked side,
roll ±150°, sphere centre and both marks at least 20 px inside the 640×480 image). Sets:
``s_cc``, ``s_n``, ``s`` and the point-based IBVS baseline (``core/ibvs.py``). Conditions:

=========  =================================================================  ===========
ideal      exact radius and intrinsics                                        exact obs.
rhat_0.5   r̂ = 0.5 r                                                           exact obs.
rhat_2     r̂ = 2 r                                                             exact obs.
calib      controller intrinsics +35 % px, +30 % py, −25 % u0, +27 % v0        exact obs.
noise      σ = 1 px Gaussian noise on 64 contour points and on the marks       exact obs.
images     rendered images (grey-level noise σ = 2) + the real detector       renderer+detector
balloon    ellipsoid 6 × 5.5 × 4.5 cm, r̂ = 6.5 cm (s_cc n/a: no tangent tip)  exact obs.
=========  =================================================================  ===========

"exact obs." is the analytic image (``core/observers.exact_observer``): same geometry as the
detector's output, ~20× faster; ``images`` runs the first ``--n-images`` starts only.
Free-flying camera, dt = 0.1 s, ViSP adaptive gain, at most 400 iterations.

A run succeeds when ‖s − s*‖ falls under the tolerance, the final pose is within 5 mm / 1°
of the desired one (1 cm / 2° with noise) and the sphere centre and both marks stayed in
the image all along. Results are appended per run to ``runs.jsonl`` (a rerun with
``--resume`` skips the cells already done); ``study.md`` and ``study.png`` summarise them.
"""
from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import sys
import time
from pathlib import Path

import numpy as np

from ..core import ibvs  # noqa: F401  (registers 'ibvs')
from ..core.camera import CameraIntrinsics
from ..core.geometry import GeometryError
from ..core.loop import run_loop
from ..core.measurement import observe
from ..core.observers import exact_observer, image_observer
from ..core.scenarios import CMO_DESIRED, camera_at
from ..core.targets import balloon, cc_target
from .paper import ADAPTIVE, CALIB_ERROR, DT

SETS = ('s_cc', 's_n', 's', 'ibvs')
CONDITIONS = ('ideal', 'rhat_0.5', 'rhat_2', 'calib', 'noise', 'images', 'balloon')
MAX_ITER = 400
CAM = CameraIntrinsics()


def start_poses(n: int, seed: int = 0, margin_px: float = 20.0) -> list:
    """``n`` random ``cMo`` with the CC target's sphere centre and marks in the image."""
    rng = np.random.default_rng(seed)
    target = cc_target()
    poses = []
    while len(poses) < n:
        d = rng.uniform(0.3, 0.7)
        u = rng.normal(size=3)
        u[2] = -abs(u[2]) - 0.7  # the marked cap faces −z
        cMo = camera_at(d * u / np.linalg.norm(u), rng.uniform(-150, 150),
                        rng.normal(size=3) * 0.02)
        try:
            obs = observe(cMo, target)
        except GeometryError:
            continue
        rays = np.array([obs.sphere.b, *obs.q.values()])
        if np.all(CAM.in_image(CAM.project(rays), margin=margin_px)):
            poses.append(cMo)
    return poses


def run_cell(task: tuple) -> dict:
    """One run: ``(condition, set, index, cMo homogeneous)`` → a JSON-able row."""
    cond, fs, idx, M = task
    import pinocchio as pin
    cMo = pin.SE3(np.asarray(M))
    target = balloon() if cond == 'balloon' else cc_target()
    ctrl_cam = CAM.with_error(**CALIB_ERROR) if cond == 'calib' else CAM
    r_hat = {'rhat_0.5': 0.5 * target.radius, 'rhat_2': 2.0 * target.radius,
             'balloon': 0.065}.get(cond, target.radius)
    if cond == 'images':
        obs, tol = image_observer(target, CAM, noise_sigma=2.0, seed=idx), 1e-3
    elif cond == 'noise':
        obs, tol = exact_observer(target, CAM, pixel_noise=1.0, seed=idx), 1e-3
    else:
        obs, tol = exact_observer(target, CAM, None if ctrl_cam is CAM else ctrl_cam), 1e-4
    t0 = time.perf_counter()
    try:
        obs(cMo)  # run_loop cannot report a failure of the very first observation
        res = run_loop(target, cMo, CMO_DESIRED, fs, r_hat=r_hat, gain=ADAPTIVE, dt=DT,
                       max_iter=250 if cond in ('noise', 'images') else MAX_ITER, tol=tol, observer=obs, camera=ctrl_cam)
    except (GeometryError, ValueError) as exc:  # noqa: B014
        # ValueError: run_loop cannot build its result when the very first observation
        # fails (0 iterations) — the target is not observable from this start
        return dict(cond=cond, set=fs, idx=idx, success=False, converged=False,
                    reason=f'target lost at the start: {exc}',
                    left_image=False, iterations=0, path=0.0, straight=1.0, seconds=time.perf_counter() - t0)
    et, er = res.final_pose_error()
    noisy = cond in ('noise', 'images')
    pose_ok = et < (0.01 if noisy else 0.005) and er < (2.0 if noisy else 1.0)
    left = bool(res.in_view is not None and not np.all(res.in_view))
    # with noise ‖s − s*‖ may never fall under tol: there the final pose decides
    conv = bool(pose_ok and (res.converged or (noisy and res.reason == 'max_iter')))
    return dict(cond=cond, set=fs, idx=idx, converged=conv,
                success=bool(conv and not left), left_image=left,
                reason=res.reason if res.converged or 'lost' in res.reason else
                f'{res.reason} (‖e‖={np.linalg.norm(res.e[-1]):.2g})',
                iterations=res.iterations, path=res.path_length,
                straight=res.straight_distance, final_t_mm=et * 1e3, final_r_deg=er,
                seconds=time.perf_counter() - t0)


def tasks(n: int, n_images: int, seed: int) -> list:
    poses = start_poses(n, seed)
    out = []
    for cond in CONDITIONS:
        for idx, cMo in enumerate(poses[:n_images] if cond == 'images' else poses):
            for fs in SETS:
                if cond == 'balloon' and fs == 's_cc':
                    continue
                out.append((cond, fs, idx, cMo.homogeneous.tolist()))
    return out


def load(path: Path) -> list:
    if not path.exists():
        return []
    rows = []
    for line in path.read_text().splitlines():
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError:  # a line cut by an interrupt
            continue
    return rows


def run_study(n: int = 500, n_images: int = 50, out: Path = Path('docs/study'),
              resume: bool = False, workers: int = 2, seed: int = 0,
              log=sys.stdout) -> list:
    """Run (or finish, with ``resume``) the study; returns every row."""
    out.mkdir(parents=True, exist_ok=True)
    path = out / 'runs.jsonl'
    if not resume and path.exists():
        path.unlink()
    rows = load(path)
    done = {(r['cond'], r['set'], r['idx']) for r in rows}
    todo = [t for t in tasks(n, n_images, seed) if t[:3] not in done]
    log.write(f'[study] {len(done)} runs done, {len(todo)} to go, {workers} worker(s)\n')
    t0, last = time.perf_counter(), -1
    with path.open('a') as f, mp.get_context('fork').Pool(workers) as pool:
        for k, row in enumerate(pool.imap_unordered(run_cell, todo, chunksize=4), 1):
            f.write(json.dumps(row) + '\n')
            f.flush()
            rows.append(row)
            pct = 5 * int(20 * k / len(todo))
            if pct != last:
                last = pct
                el = time.perf_counter() - t0
                bar = '#' * (pct // 4) + '.' * (25 - pct // 4)
                log.write(f'[study] [{bar}] {pct:3d}% {k}/{len(todo)} {el:6.0f} s, '
                          f'eta {el / k * (len(todo) - k):5.0f} s\n')
                log.flush()
    log.write(f'[study] {len(todo)} runs in {time.perf_counter() - t0:.0f} s\n')
    return rows


def summarize(rows: list) -> dict:
    """Per (condition, set): n, success %, median iterations (successes), median
    path/straight (converged runs), left-image %, failure reasons."""
    cells = {}
    for r in rows:
        cells.setdefault((r['cond'], r['set']), []).append(r)
    out = {}
    for key, rs in cells.items():
        ok = [r for r in rs if r['success']]
        conv = [r for r in rs if r.get('converged')]
        reasons = {}
        for r in rs:
            if not r['success']:
                why = 'left the image' if r['converged'] else r['reason'].split(' (')[0]
                why = why.split(':')[0] + (': ' + why.split(':')[1].strip() if ':' in why
                                           else '')
                reasons[why] = reasons.get(why, 0) + 1
        out[key] = dict(
            n=len(rs), success=100.0 * len(ok) / len(rs),
            iters=float(np.median([r['iterations'] for r in ok])) if ok else float('nan'),
            ratio=float(np.median([r['path'] / r['straight'] for r in conv])) if conv
            else float('nan'),
            left=100.0 * sum(r.get('left_image', False) for r in rs) / len(rs),
            reasons=reasons, seconds=float(np.sum([r['seconds'] for r in rs])))
    return out


def sn_shorter_fraction(rows: list, cond: str = 'ideal') -> tuple[float, int]:
    """Fraction of starts (both converged) where s_n's camera path is shorter than s_cc's."""
    by = {}
    for r in rows:
        if r['cond'] == cond and r['set'] in ('s_n', 's_cc') and r.get('converged'):
            by.setdefault(r['idx'], {})[r['set']] = r['path']
    pairs = [v for v in by.values() if len(v) == 2]
    return (sum(v['s_n'] < v['s_cc'] for v in pairs) / len(pairs) if pairs else float('nan'),
            len(pairs))


def plot(summary: dict, path: Path) -> Path:
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    from .plots import save
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(12, 3.8))
    w = 0.2
    x = np.arange(len(CONDITIONS))
    for k, fs in enumerate(SETS):
        succ = [summary.get((c, fs), {}).get('success', np.nan) for c in CONDITIONS]
        rat = [summary.get((c, fs), {}).get('ratio', np.nan) for c in CONDITIONS]
        a1.bar(x + (k - 1.5) * w, succ, w, label=fs)
        a2.bar(x + (k - 1.5) * w, rat, w, label=fs)
    for a, lab in ((a1, 'success rate (%)'), (a2, 'median camera path / straight distance')):
        a.set_xticks(x, CONDITIONS, fontsize=8)
        a.set_xlabel('condition')
        a.set_ylabel(lab)
        a.grid(alpha=0.3, axis='y')
        a.legend(fontsize=8)
    a2.set_ylim(0.9, None)
    save(fig, path, dpi=90)
    from .paper import shrink_png
    return shrink_png(path)


def write_report(rows: list, out: Path, n: int, n_images: int, wall: float | None,
                 workers: int) -> Path:
    s = summarize(rows)
    frac, npairs = sn_shorter_fraction(rows)
    cpu = sum(v['seconds'] for v in s.values())
    nrun = sum(v['n'] for v in s.values())
    lines = ['# Monte Carlo study of the feature sets', '',
             f'Generated by `python -m sphere_servo.tools.study --n {n} --n-images '
             f'{n_images}` ({nrun} runs; see the module docstring for the setup). '
             f'Compute: {cpu:.0f} s of run time in total, {1e3 * cpu / max(nrun, 1):.0f} ms '
             'per run' + (f'; wall clock {wall:.0f} s with {workers} workers.' if wall
                          else '.'), '',
             'Observation: **exact** (analytic image, `core/observers.exact_observer`) for '
             'ideal, r̂, calib, noise (σ = 1 px on contour points and marks, conic re-fitted) '
             'and balloon; **rendered images + detector** for `images` '
             f'(first {n_images} starts, grey-level noise σ = 2).', '',
             '| condition | set | runs | success | median iterations | median path / '
             'straight | target left the image | joint-limit hits |',
             '|---|---|---|---|---|---|---|---|']
    for c in CONDITIONS:
        for fs in SETS:
            v = s.get((c, fs))
            if v is None:
                if c == 'balloon' and fs == 's_cc':
                    lines.append(f'| {c} | {fs} | — | n/a (no tangent tip on the balloon) '
                                 '| | | | |')
                continue
            lines.append(f"| {c} | {fs} | {v['n']} | {v['success']:.1f} % | "
                         f"{v['iters']:.0f} | {v['ratio']:.3f} | {v['left']:.1f} % | n/a |")
    lines += ['', 'Joint-limit hits are n/a: the study servos a free-flying camera (the arm '
              'triples the cost, and the UR5\'s own ±2π / ±π limits are met by no set from '
              'any start we sampled — see docs/paper, joint-limit scenario).', '',
              f's_n draws a shorter camera path than s_cc in **{100 * frac:.1f} %** of the '
              f'{npairs} ideal starts where both converge (the paper\'s §IV.A.2 claim holds '
              'for most starts, not all).', '', '![study](study.png)', '',
              '## Failures by cause', '', '| condition | set | cause | runs |', '|---|---|---|---|']
    for (c, fs), v in sorted(s.items()):
        for why, k in sorted(v['reasons'].items(), key=lambda kv: -kv[1]):
            lines.append(f'| {c} | {fs} | {why} | {k} |')
    plot(s, out / 'study.png')
    path = out / 'study.md'
    path.write_text('\n'.join(lines) + '\n')
    return path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--n', type=int, default=500, help='start poses')
    ap.add_argument('--n-images', type=int, default=50,
                    help='starts of the rendered-images condition')
    ap.add_argument('--out', default='docs/study', help='folder of runs.jsonl and study.md')
    ap.add_argument('--resume', action='store_true', help='skip the runs already done')
    ap.add_argument('--workers', type=int, default=2)
    ap.add_argument('--seed', type=int, default=0)
    args = ap.parse_args(argv)
    out = Path(args.out)
    t0 = time.perf_counter()
    rows = run_study(args.n, min(args.n_images, args.n), out, args.resume, args.workers,
                     args.seed)
    wall = time.perf_counter() - t0
    rep = write_report(rows, out, args.n, min(args.n_images, args.n),
                       None if args.resume else wall, args.workers)
    print(f'[study] wrote {rep}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
