"""Douglas–Peucker's plain-Python path for short 2-D polylines keeps exactly the points its numpy
path keeps (issue 16: a route's legs are simplified on every request)."""

from __future__ import annotations

import numpy as np
import pytest

from app.domain.navigation.path_graph import geometry
from app.domain.navigation.path_graph.geometry import SMALL_POLYLINE_POINTS, douglas_peucker


def numpy_douglas_peucker(
    points: np.ndarray, tolerance_m: float, monkeypatch: pytest.MonkeyPatch
) -> np.ndarray:
    with monkeypatch.context() as patched:
        patched.setattr(geometry, "SMALL_POLYLINE_POINTS", 0)
        return douglas_peucker(points, tolerance_m)


def polylines() -> list[np.ndarray]:
    """Random walks, grid points (exact ties of distance), repeated points, a straight line, a
    closed loop, and the largest polyline the plain path takes."""
    rng = np.random.default_rng(16)
    cases = [np.cumsum(rng.normal(size=(n, 2)) * 3.0, axis=0) for n in range(3, 60)]
    cases += [rng.integers(-3, 4, size=(n, 2)).astype(np.float64) for n in range(3, 40)]
    cases.append(np.array([[0.0, 0.0], [0.0, 0.0], [0.0, 0.0], [1.0, 1.0]]))
    cases.append(np.array([[1.0, 1.0], [5.0, 2.0], [1.0, 1.0]]))  # first == last
    cases.append(np.column_stack([np.arange(10.0), 2.0 * np.arange(10.0)]))
    cases.append(np.cumsum(rng.normal(size=(SMALL_POLYLINE_POINTS, 2)), axis=0))
    return cases


@pytest.mark.parametrize("tolerance_m", [0.0, 0.4, 0.5, 1.0, 3.0])
def test_short_polylines_keep_what_the_numpy_path_keeps(tolerance_m, monkeypatch):
    for points in polylines():
        want = numpy_douglas_peucker(points, tolerance_m, monkeypatch)
        got = douglas_peucker(points, tolerance_m)
        assert got.dtype == np.bool_
        np.testing.assert_array_equal(got, want, err_msg=str(points.tolist()))


def test_a_tolerance_equal_to_a_distance_drops_the_point():
    points = np.array([[0.0, 0.0], [1.0, 0.5], [2.0, 0.0]])
    assert douglas_peucker(points, 0.5).tolist() == [True, False, True]
    assert douglas_peucker(points, 0.4999).tolist() == [True, True, True]


def test_a_nan_point_is_dropped_as_by_numpy(monkeypatch):
    points = np.array([[0.0, 0.0], [5.0, 9.0], [np.nan, 1.0], [7.0, -9.0], [9.0, 0.0]])
    want = numpy_douglas_peucker(points, 0.5, monkeypatch)
    np.testing.assert_array_equal(douglas_peucker(points, 0.5), want)


def test_three_dimensional_and_long_polylines_take_the_numpy_path(monkeypatch):
    rng = np.random.default_rng(3)
    long = np.cumsum(rng.normal(size=(SMALL_POLYLINE_POINTS + 50, 2)), axis=0)
    spatial = np.cumsum(rng.normal(size=(30, 3)), axis=0)
    for points in (long, spatial):
        kept = douglas_peucker(points, 0.5)
        np.testing.assert_array_equal(kept, numpy_douglas_peucker(points, 0.5, monkeypatch))
        assert kept[0]
        assert kept[-1]
