"""Small geometry helpers shared by the builder and the exporters (horizontal x–z and 3-D)."""

from __future__ import annotations

import networkx as nx
import numpy as np
import numpy.typing as npt

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
