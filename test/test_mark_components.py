"""The marks' labelling gives what OpenCV's connectedComponentsWithStats gives."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from sphere_servo.vision.marks import components


def _masks():
    """Yield seeded 0/1 masks: blobs, speckle, thin lines, one row or column, one pixel."""
    rng = np.random.default_rng(7)
    for k in range(300):
        h, w = int(rng.integers(1, 40)), int(rng.integers(1, 40))
        m = (rng.uniform(size=(h, w)) < rng.uniform(0.02, 0.9)).astype(np.uint8)
        if k % 3 == 0:                      # a few solid blobs and touching corners
            m[:] = 0
            for _ in range(int(rng.integers(1, 4))):
                y, x = int(rng.integers(h)), int(rng.integers(w))
                m[y:y + int(rng.integers(1, 12)), x:x + int(rng.integers(1, 12))] = 1
        if m.any():
            yield m
    yield np.ones((1, 1), np.uint8)
    yield np.eye(12, dtype=np.uint8)                    # diagonal: one 8-connected line
    yield np.eye(12, dtype=np.uint8)[::-1].copy()       # the other diagonal
    yield np.kron(np.eye(6, dtype=np.uint8), np.ones((2, 2), np.uint8))
    yield np.pad(np.eye(9, dtype=np.uint8)[::2], ((0, 0), (1, 3)))   # separate pixels


@pytest.mark.parametrize('m', list(_masks()), ids=lambda m: f'{m.shape}:{int(m.sum())}')
def test_components_are_opencvs(m):
    nlab, lab, st, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
    got_n, got_lab, got_st = components(m.copy(), int(np.count_nonzero(m)))
    assert got_n == nlab
    if nlab > 2:                            # the labels and stats are read only then
        on = m > 0
        assert np.array_equal(got_lab[on], lab[on])
        assert np.array_equal(got_st[1:], st[1:])
