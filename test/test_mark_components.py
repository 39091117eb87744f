"""The marks' labelling and hull give what OpenCV gives for all of a mark's pixels."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from sphere_servo.vision.image import row_ends
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


def _filled(hull: np.ndarray, shape) -> np.ndarray:
    out = np.zeros(shape, np.uint8)
    cv2.fillConvexPoly(out, hull, 1)
    return out


@pytest.mark.parametrize('m', list(_masks()), ids=lambda m: f'{m.shape}:{int(m.sum())}')
def test_the_hull_of_row_ends_is_the_pixels_hull(m):
    # the pixels as the marks find them (cv2.findNonZero: row-major)
    pts = cv2.findNonZero(m).reshape(-1, 2)
    ends = row_ends(pts)
    assert len(ends) <= 2 * len(np.unique(pts[:, 1]))
    whole, fast = cv2.convexHull(pts), cv2.convexHull(ends)
    assert {tuple(p) for p in whole.reshape(-1, 2).tolist()} == \
        {tuple(p) for p in fast.reshape(-1, 2).tolist()}
    assert cv2.boundingRect(fast) == cv2.boundingRect(pts)
    shape = (m.shape[0] + 2, m.shape[1] + 2)
    assert np.array_equal(_filled(fast, shape), _filled(whole, shape))
