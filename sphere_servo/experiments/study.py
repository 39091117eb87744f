"""
``make study``: Monte Carlo study of the feature sets over random start poses.

    python -m sphere_servo.experiments.study [--n 500] [--n-images 50] [--out docs/study]
                                             [--resume] [--workers 2] [--seed 0]

The setup (start poses, sets, conditions, when a run succeeds) is
:mod:`~sphere_servo.experiments.study_cells`'s; the summary and its text
:mod:`~sphere_servo.experiments.study_report`'s. Results are appended per run to
``runs.jsonl`` (a rerun with ``--resume`` skips the cells already done); ``study.md`` and
``study.png`` summarise them.
"""
from __future__ import annotations

import argparse
import json
import multiprocessing as mp
from pathlib import Path
import sys
import time

from sphere_servo.experiments import study_cells as cells
from sphere_servo.experiments.study_report import write_report


def load(path: Path) -> list:
    """Read the rows of a ``runs.jsonl`` ([] if there is none)."""
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
    """Run (or finish, with ``resume``) the study; return every row."""
    out.mkdir(parents=True, exist_ok=True)
    path = out / 'runs.jsonl'
    if not resume and path.exists():
        path.unlink()
    rows = load(path)
    done = {(r['cond'], r['set'], r['idx']) for r in rows}
    todo = [t for t in cells.tasks(n, n_images, seed) if t[:3] not in done]
    log.write(f'[study] {len(done)} runs done, {len(todo)} to go, {workers} worker(s)\n')
    t0, last = time.perf_counter(), -1
    with path.open('a') as f, mp.get_context('fork').Pool(workers) as pool:
        for k, row in enumerate(pool.imap_unordered(cells.run_cell, todo, chunksize=4), 1):
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


def main(argv=None) -> int:
    """Run the study and write its report."""
    ap = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    ap.add_argument('--n', type=int, default=500, help='start poses')
    ap.add_argument('--n-images', type=int, default=50,
                    help='starts of the rendered-images condition')
    ap.add_argument('--out', default='docs/study', help='folder of runs.jsonl and study.md')
    ap.add_argument('--resume', action='store_true', help='skip the runs already done')
    ap.add_argument('--workers', type=int, default=2)
    ap.add_argument('--seed', type=int, default=0)
    args = ap.parse_args(argv)
    out = Path(args.out)
    resumed = len(load(out / 'runs.jsonl')) if args.resume else 0
    t0 = time.perf_counter()
    rows = run_study(args.n, min(args.n_images, args.n), out, args.resume, args.workers,
                     args.seed)
    wall = time.perf_counter() - t0
    # the wall clock says how long the study takes only if this call ran every run
    rep = write_report(rows, out, args.n, min(args.n_images, args.n),
                       None if resumed else wall, args.workers)
    print(f'[study] wrote {rep}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
