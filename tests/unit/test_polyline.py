"""The plain-Python measures of a route's polyline give the bits of the numpy expressions they
stand for, and Douglas–Peucker's end legs are the ones the full simplification keeps (issue 16:
a route's steps must not change when they are made cheaper)."""

from __future__ import annotations

import numpy as np
import pytest

from app.domain.navigation.path_graph.geometry import (
    SMALL_POLYLINE_POINTS,
    douglas_peucker,
    douglas_peucker_end_legs,
)
from app.domain.navigation.polyline import distances_along_m, point_along, segment_lengths_m


def polylines() -> list[np.ndarray]:
    """(N, 3) random walks at several scales, far from the origin, with repeated points, on a
    grid (exact ties), and longer than the plain-Python Douglas–Peucker takes."""
    rng = np.random.default_rng(16)
    cases = []
    for n in [*range(1, 30), 60, SMALL_POLYLINE_POINTS + 5, 250]:
        for scale in (1e-3, 1.0, 40.0):
            points = np.cumsum(rng.normal(size=(n, 3)) * scale, axis=0) + rng.normal(size=3) * 1e3
            if n > 3:
                points[rng.integers(1, n)] = points[rng.integers(0, n)]
            cases.append(points)
        cases.append(rng.integers(-3, 4, size=(n, 3)).astype(np.float64))
    cases.append(np.zeros((5, 3)))
    return cases


def test_lengths_and_distances_along_are_numpys_to_the_bit():
    for xyz in polylines():
        lengths_m = np.linalg.norm(np.diff(xyz, axis=0), axis=1)
        points = [(x, y, z) for x, y, z in xyz.tolist()]
        assert segment_lengths_m(points) == lengths_m.tolist()
        walked_m = np.concatenate([[0.0], np.cumsum(lengths_m)])
        assert distances_along_m(segment_lengths_m(points)) == walked_m.tolist()


def numpy_point_along(xyz: np.ndarray, walked_m: np.ndarray, along_m: float) -> np.ndarray:
    """The interpolation steps did with numpy before (issue 16)."""
    k = min(max(int(np.searchsorted(walked_m, along_m)) - 1, 0), len(xyz) - 2)
    span = float(walked_m[k + 1] - walked_m[k])
    t = 0.0 if span == 0 else (along_m - float(walked_m[k])) / span
    return np.asarray(xyz[k] + t * (xyz[k + 1] - xyz[k]), dtype=np.float64)


def test_a_point_along_is_the_numpy_interpolation_to_the_bit():
    rng = np.random.default_rng(7)
    for xyz in polylines():
        if len(xyz) < 2:
            continue
        points = [(x, y, z) for x, y, z in xyz.tolist()]
        walked = distances_along_m(segment_lengths_m(points))
        walked_m = np.array(walked)
        alongs = [*walked, -1.0, walked[-1] + 1.0, *rng.uniform(0.0, walked[-1], size=20)]
        for along_m in alongs:
            want = numpy_point_along(xyz, walked_m, float(along_m)).tolist()
            assert list(point_along(points, walked, float(along_m))) == want


@pytest.mark.parametrize("tolerance_m", [0.0, 0.3, 0.5, 1.0, 5.0])
def test_the_end_legs_are_those_of_the_full_simplification(tolerance_m):
    for xyz in polylines():
        if len(xyz) < 2:
            continue
        xz = xyz[:, [0, 2]]
        kept = np.flatnonzero(douglas_peucker(xz, tolerance_m)).tolist()
        got = douglas_peucker_end_legs(xz[:, 0].tolist(), xz[:, 1].tolist(), tolerance_m)
        assert got == (kept[1], kept[-2]), (tolerance_m, xz.tolist())


def test_the_end_legs_of_a_hand_worked_zigzag():
    """0 → 4 along x, tolerance 1 m. Bumps of 2 m at 1 and 3: every point is kept. A bump of
    0.5 m at 1 and of 2 m at 3: 3 is kept, then 2 (1.1 m off the line 0–3), not 1 (0.5 m off
    0–2), so the first leg is 0–2 and the last 3–4."""
    xs = [0.0, 1.0, 2.0, 3.0, 4.0]
    assert douglas_peucker_end_legs(xs, [0.0, 2.0, 0.0, 2.0, 0.0], 1.0) == (1, 3)
    assert douglas_peucker_end_legs(xs, [0.0, 0.5, 0.0, 2.0, 0.0], 1.0) == (2, 3)
    assert douglas_peucker_end_legs(xs, [0.0] * 5, 1.0) == (4, 0)
    assert douglas_peucker_end_legs([0.0, 1.0], [0.0, 0.0], 1.0) == (1, 0)
