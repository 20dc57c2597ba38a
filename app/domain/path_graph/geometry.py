"""Small geometry helpers shared by the builder and the exporters (horizontal x–z and 3-D)."""

from __future__ import annotations

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


def points_array(values: npt.ArrayLike | None, count: int, name: str) -> FloatArray:
    """``values`` as (count, 3) points (none for None); ParameterError naming ``name`` if there
    are not as many rows as names."""
    points = np.empty((0, 3)) if values is None else np.asarray(values, dtype=np.float64)
    points = points.reshape(-1, 3)
    if points.shape[0] != count:
        raise ParameterError(f"{name} has {points.shape[0]} rows for {count} names")
    return points
