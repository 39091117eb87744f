"""
``make bench``: every speed benchmark of the project in one run, as one table.

The table has the baseline measured beside each figure and their ratio. Benchmarks print;
tests never assert on wall-clock time.

Each area provides ``benchmarks.bench_<area>.run(quick) -> list[dict]`` with rows
``{name, value, unit, baseline, baseline_name, ratio, target}``.
"""
from __future__ import annotations

import argparse
import importlib
import sys
import traceback

AREAS = ('core', 'vision', 'arm', 'bag', 'loop', 'transport', 'paper')


def _fmt(x) -> str:
    if x is None:
        return '—'
    return f'{x:.3g}' if isinstance(x, float) else str(x)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description='run every benchmark and print one table')
    ap.add_argument('--quick', action='store_true', help='fewer repetitions')
    ap.add_argument('areas', nargs='*', default=list(AREAS), help=f'subset of {AREAS}')
    args = ap.parse_args(argv)
    rows, failed = [], []
    for area in args.areas:
        try:
            mod = importlib.import_module(f'benchmarks.bench_{area}')
        except ModuleNotFoundError as exc:
            if exc.name != f'benchmarks.bench_{area}':
                raise
            print(f'[bench] {area}: no benchmark module yet, skipped', flush=True)
            continue
        print(f'[bench] {area} …', flush=True)
        try:
            rows += mod.run(quick=args.quick)
        except Exception:  # one broken benchmark must not hide the others
            traceback.print_exc()
            failed.append(area)
    head = ('benchmark', 'value', 'unit', 'baseline (name)', 'ratio', 'target')
    table = [head] + [(r['name'], _fmt(r['value']), r['unit'],
                       f"{_fmt(r.get('baseline'))} ({r.get('baseline_name') or '—'})",
                       _fmt(r.get('ratio')), r.get('target', '')) for r in rows]
    widths = [max(len(str(row[i])) for row in table) for i in range(len(head))]
    print()
    for k, row in enumerate(table):
        print(' | '.join(str(c).ljust(w) for c, w in zip(row, widths)))
        if k == 0:
            print('-+-'.join('-' * w for w in widths))
    if failed:
        print(f'\nbenchmarks that raised: {", ".join(failed)}')
    return 1 if failed else 0


if __name__ == '__main__':
    sys.exit(main())
