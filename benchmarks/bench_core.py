"""
Benchmark of the pure core: one control step from a measurement to the twist.

From the measurement (conic + two mark points in normalized coordinates) to ``s_n``,
``L_sn`` and ``v_c``. Target (issue 2): < 100 µs median per call. Baseline beside it: a
bare 6×6 ``np.linalg.solve`` (the floor of any law that inverts L).
"""
from __future__ import annotations

import time

import numpy as np

from sphere_servo.core.control import Controller
from sphere_servo.core.features import make_feature_set
from sphere_servo.core.measurement import Observation, observe, sphere_from_conic, unit_ray
from sphere_servo.core.targets import special_sphere
from sphere_servo.experiments.scenarios import CMO_DESIRED, CMO_FAR_START


def _median_us(fn, n: int) -> float:
    times = []
    for _ in range(n):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1e6)


def run(quick: bool = False) -> list[dict]:
    n = 2000 if quick else 20000
    target = special_sphere()
    ctrl = Controller(make_feature_set('s_n', observe(CMO_DESIRED, target)), target.radius)
    obs = observe(CMO_FAR_START, target)
    b, rd = obs.sphere.b, obs.sphere.r_delta
    conic = np.outer(b, b) - (1 - rd * rd) * np.eye(3)
    marks = {k: q[:2] / q[2] for k, q in obs.q.items()}

    def step():
        sph = sphere_from_conic(conic)
        o = Observation(sph, {k: unit_ray(xy) for k, xy in marks.items()}, obs.kind)
        return ctrl.compute(o).v_c

    L = ctrl.L_hat(obs)
    e = ctrl.features.error(obs)
    t_step = _median_us(step, n)
    t_base = _median_us(lambda: np.linalg.solve(L, e), n)
    return [{'name': 'core: measurement → s_n, L_sn, twist', 'value': t_step, 'unit': 'µs',
             'baseline': t_base, 'baseline_name': 'np.linalg.solve 6×6',
             'ratio': t_step / t_base, 'target': '< 100 µs median'}]


if __name__ == '__main__':
    for row in run():
        print(row)
