"""Small geometry helpers shared by the builder and the exporters (horizontal x–z and 3-D)."""

from __future__ import annotations

import math
from collections.abc import Sequence

import networkx as nx
import numpy as np
import numpy.typing as npt

from app.domain.errors import ParameterError
from app.domain.frames import FloatArray


def node_position(G: nx.Graph[int], node: int) -> FloatArray:
    return np.asarray(G.nodes[node]["position_m"], dtype=np.float64)


def tuple3(values: npt.ArrayLike) -> tuple[float, float, float]:
    x, y, z = (float(v) for v in np.asarray(values, dtype=np.float64).reshape(3))
    return (x, y, z)


def cross_2d(p: FloatArray, q: FloatArray) -> FloatArray:
    return np.asarray(p[:, 0] * q[:, 1] - p[:, 1] * q[:, 0], dtype=np.float64)


def project_to_segments(
    points: FloatArray, a: FloatArray, b: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """(t, distance) of the nearest point a + t (b − a), t in [0, 1], to each point (broadcast)."""
    d = b - a
    length2 = np.sum(d * d, axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(length2 > 0, np.sum((points - a) * d, axis=-1) / length2, 0.0)
    t = np.clip(t, 0.0, 1.0)
    nearest = a + t[..., None] * d
    return t, np.linalg.norm(points - nearest, axis=-1)


def douglas_peucker(points: FloatArray, tolerance_m: float) -> npt.NDArray[np.bool_]:
    """(M,) which of the (M, D) points of a polyline to keep (the first and the last always) so
    that no dropped point is farther than ``tolerance_m`` from the kept segment spanning it."""
    m = points.shape[0]
    kept = np.ones(m, dtype=np.bool_)
    if m <= 2:
        return kept
    if m <= SMALL_POLYLINE_POINTS and points.ndim == 2 and points.shape[1] == 2:
        kept[1:-1] = False
        kept[_douglas_peucker_small_2d(points.tolist(), tolerance_m)] = True
        return kept
    kept[1:-1] = False
    stack = [(0, m - 1)]
    while stack:
        s, e = stack.pop()
        if e - s < 2:
            continue
        distance_m = project_to_segments(points[s + 1 : e], points[s][None], points[e][None])[1]
        k = int(np.argmax(distance_m))
        if distance_m[k] > tolerance_m:
            kept[s + 1 + k] = True
            stack += [(s, s + 1 + k), (s + 1 + k, e)]
    return kept


#: Up to this many points, :func:`douglas_peucker` of a 2-D polyline runs in plain Python, which
#: for a route's few dozen points costs a fraction of numpy's per-call overhead.
SMALL_POLYLINE_POINTS = 96


def _douglas_peucker_small_2d(points: list[list[float]], tolerance_m: float) -> list[int]:
    """The inner points :func:`douglas_peucker` keeps, for (M, 2) points as lists: the same
    floating-point operations in the same order as :func:`project_to_segments` (so the same
    distances to the last bit, and the same points kept)."""
    kept: list[int] = []
    xs = [p[0] for p in points]
    ys = [p[1] for p in points]
    stack = [(0, len(points) - 1)]
    while stack:
        s, e = stack.pop()
        if e - s < 2:
            continue
        k, distance_m = _farthest_2d(xs, ys, s, e)
        if distance_m > tolerance_m:
            kept.append(k)
            stack += [(s, k), (k, e)]
    return kept


def douglas_peucker_end_legs(
    xs: Sequence[float], ys: Sequence[float], tolerance_m: float
) -> tuple[int, int]:
    """(the second, the second-to-last) of the indices :func:`douglas_peucker` keeps of M ≥ 2
    2-D points ``xs``, ``ys``: where the first kept leg ends and the last one starts. Only the
    splits that lead to them are made, with the distances :func:`douglas_peucker` computes, so
    they are the points it keeps."""
    last = len(xs) - 1
    first_end, last_start = last, 0
    if last >= 2:
        k, distance_m = _farthest_2d(xs, ys, 0, last)
        if distance_m > tolerance_m:
            first_end = last_start = k
            while first_end >= 2:  # split (0, first_end): its kept points come first
                k, distance_m = _farthest_2d(xs, ys, 0, first_end)
                if not distance_m > tolerance_m:
                    break
                first_end = k
            while last - last_start >= 2:  # split (last_start, last): its kept points come last
                k, distance_m = _farthest_2d(xs, ys, last_start, last)
                if not distance_m > tolerance_m:
                    break
                last_start = k
    return first_end, last_start


def _farthest_2d(xs: Sequence[float], ys: Sequence[float], s: int, e: int) -> tuple[int, float]:
    """(index, distance) of the inner point of s…e (e − s ≥ 2) farthest from the segment s–e, the
    first of equals (a NaN distance is the farthest), as :func:`project_to_segments` and
    ``np.argmax`` find it. A square root is taken only when it may be the largest so far."""
    sqrt = math.sqrt
    ax, ay = xs[s], ys[s]
    dx, dy = xs[e] - ax, ys[e] - ay
    length2 = dx * dx + dy * dy
    best_k, best_m, best_q2 = -1, -1.0, -1.0
    for k in range(s + 1, e):
        px, py = xs[k], ys[k]
        t = ((px - ax) * dx + (py - ay) * dy) / length2 if length2 > 0 else 0.0
        t = 0.0 if t < 0.0 else 1.0 if t > 1.0 else t
        qx = px - (ax + t * dx)
        qy = py - (ay + t * dy)
        q2 = qx * qx + qy * qy
        if q2 > best_q2:  # else its distance is at most the best's
            distance_m = sqrt(q2)
            if distance_m > best_m:
                best_k, best_m, best_q2 = k, distance_m, q2
        elif q2 != q2:  # NaN: numpy's argmax picks the first, never kept
            return k, q2
    return best_k, best_m


def points_array(values: npt.ArrayLike | None, count: int, name: str) -> FloatArray:
    """``values`` as (count, 3) points (none for None); ParameterError naming ``name`` if there
    are not as many rows as names."""
    points = np.empty((0, 3)) if values is None else np.asarray(values, dtype=np.float64)
    points = points.reshape(-1, 3)
    if points.shape[0] != count:
        raise ParameterError(f"{name} has {points.shape[0]} rows for {count} names")
    return points
