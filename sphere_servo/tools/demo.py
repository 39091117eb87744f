"""``make demo``: the paper's special-sphere scenario (§IV.A.1), then the CC-target
comparison of the three sets (§IV.A.2), run in the headless kinematic loop.

Prints progress (iteration, ‖s − s*‖) as it goes and writes Fig. 3 / Fig. 4 analogues into
``runs/<timestamp>/``; ends by printing where the files are. Exit code 0 only if every run
converged.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from ..core.loop import run_loop
from ..core.features import make_feature_set
from ..core.measurement import observe
from ..core.scenarios import CMO_DESIRED, CMO_FAR_START
from ..core.targets import cc_target, special_sphere
from .plots import fig3, fig4

def progress(res, every: int = 25) -> None:
    norms = np.linalg.norm(res.e, axis=1)
    for k in range(0, res.iterations, every):
        print(f'  [{res.feature_set:>4}] iteration {k:4d}  t={res.t[k]:6.2f} s  '
              f'‖s − s*‖ = {norms[k]:.3e}')
    dt_err, dr_err = res.final_pose_error()
    print(f'  [{res.feature_set:>4}] {res.reason} after {res.iterations} iterations; final '
          f'error {dt_err * 1000:.3f} mm, {dr_err:.4f}°; camera path {res.path_length:.3f} m '
          f'(straight {res.straight_distance:.3f} m)')


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--out', default='runs', help='parent folder of the run folder')
    ap.add_argument('--gain', type=float, default=0.5, help='λ (1/s)')
    ap.add_argument('--dt', type=float, default=0.1, help='control period (s)')
    args = ap.parse_args(argv)
    out = Path(args.out) / time.strftime('%Y%m%d-%H%M%S')
    out.mkdir(parents=True, exist_ok=True)
    ok = True
    print('§IV.A.1 special sphere, s_n (headless kinematic loop)')
    sp = special_sphere()
    res = run_loop(sp, CMO_FAR_START, CMO_DESIRED, 's_n', gain=args.gain, dt=args.dt)
    progress(res)
    ok &= res.converged
    labels = make_feature_set('s_n', observe(CMO_DESIRED, sp)).labels
    files = [fig3(res.t, res.e, res.v, labels, out / 'fig3_special_sn.png',
                  'Special sphere, s_n'),
             fig4({'s_n': res}, out / 'fig4_special_sn.png', 'Special sphere, s_n')]
    print('§IV.A.2 CC target: s_cc, s_n, s')
    cc = cc_target()
    runs = {}
    for name in ('s_cc', 's_n', 's'):
        runs[name] = run_loop(cc, CMO_FAR_START, CMO_DESIRED, name, gain=args.gain, dt=args.dt)
        progress(runs[name])
        ok &= runs[name].converged
    files.append(fig4(runs, out / 'fig4_cc_compare.png', 'CC target: s_cc, s_n, s'))
    print('\nwrote:')
    for f in files:
        print(f'  {f}')
    print('all runs converged' if ok else 'SOME RUNS DID NOT CONVERGE')
    return 0 if ok else 1


if __name__ == '__main__':
    sys.exit(main())
