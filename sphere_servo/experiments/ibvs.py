"""
Classical point-based IBVS on three image points, the baseline of the Monte Carlo study.

The points are the sphere centre's image and the two marks (no ROS). Features
``s = (x_O, y_O, x_1, y_1, x_2, y_2)``: normalized image coordinates of the sphere centre O
(``x_O = b_x/b_z``; the projection of the 3D point O, not the ellipse's centre), of P1 and
of the second mark (P2 on a special sphere, the CC tip P3). Interaction matrix of a point
at depth Z (Chaumette & Hutchinson 2006):

    L_x = [[−1/Z, 0, x/Z, xy, −(1 + x²), y], [0, −1/Z, y/Z, 1 + y², −xy, −x]]

with the depths taken from the sphere measurement and the estimated radius r̂ (DESIGN.md §2):
``Z_O = (r̂/r_δ) b_z``, ``Z_i = r̂ (‖P_i‖/r) q_i,z``. The matrix is 6×6 (three points fix the
pose up to the classical 4-solution ambiguity).

The loop takes the class itself: ``run_loop(..., feature_set=IbvsFeatures)``; importing
this module registers nothing.
"""
from __future__ import annotations

import numpy as np

from sphere_servo.core.features import check_radius, FeatureSet
from sphere_servo.core.measurement import MeasurementError, Observation, P3_over_r, P_over_r
from sphere_servo.core.targets import CC

NAME = 'ibvs'


def point_interaction(x: float, y: float, Z: float) -> np.ndarray:
    """2×6 interaction matrix of a normalized image point (x, y) at depth Z (m)."""
    iz = 1.0 / Z
    return np.array([[-iz, 0.0, x * iz, x * y, -(1.0 + x * x), y],
                     [0.0, -iz, y * iz, 1.0 + y * y, -x * y, -x]])


class IbvsFeatures(FeatureSet):
    """Image coordinates of O, P1 and P2/P3; ``interaction`` with depths from the image."""

    name = NAME
    size = 6
    labels = names = ('x_O', 'y_O', 'x_1', 'y_1', 'x_2', 'y_2')

    def _setup(self, desired: Observation) -> None:
        pass

    @staticmethod
    def _rays(obs: Observation) -> list[np.ndarray]:
        try:
            return [obs.sphere.b, obs.q['P1'], obs.q[obs.second]]
        except KeyError as exc:
            raise MeasurementError(f'mark {exc.args[0]} is not visible') from None

    def features(self, obs: Observation) -> np.ndarray:
        out = []
        for u in self._rays(obs):
            if u[2] <= 1e-9:
                raise MeasurementError('point behind the camera')
            out += [u[0] / u[2], u[1] / u[2]]
        return np.array(out)

    @staticmethod
    def depths_over_r(obs: Observation) -> np.ndarray:
        """``(Z_O, Z_1, Z_2) / r`` from the image alone."""
        sph = obs.sphere
        q1, q2 = obs.q['P1'], obs.q[obs.second]
        P1r = P_over_r(sph, q1)
        P2r = P3_over_r(sph, P1r, q2) if obs.kind == CC else P_over_r(sph, q2)
        return np.array([sph.b[2] / sph.r_delta, P1r[2], P2r[2]])

    def interaction(self, obs: Observation, r_hat: float, s=None) -> np.ndarray:
        r_hat = check_radius(r_hat)
        s = self.features(obs) if s is None else s
        Z = r_hat * self.depths_over_r(obs)
        if np.any(Z <= 0):
            raise MeasurementError(f'non-positive depth from the image: {Z}')
        return np.vstack([point_interaction(s[2 * i], s[2 * i + 1], Z[i]) for i in range(3)])
