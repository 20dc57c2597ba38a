"""A route's polyline measured with plain Python floats: for the few dozen points of a route,
numpy's cost per call is most of the work (issue 16). Each function does the floating-point
operations of the numpy expression it stands for, in the same order, so it gives the same bits.

    lengths_m = segment_lengths_m(points)    # np.linalg.norm(np.diff(xyz, axis=0), axis=1)
    walked_m = distances_along_m(lengths_m)  # np.concatenate([[0.0], np.cumsum(lengths_m)])
    point_along(points, walked_m, 12.5)      # the point 12.5 m along, interpolated
    xyz = xyz_array(points)                  # np.asarray(points, dtype=np.float64).reshape(-1, 3)

Points are (x, y, z) tuples of floats, map frame, m.
"""

from __future__ import annotations

import itertools
import math
from bisect import bisect_left
from collections.abc import Sequence
from typing import TypeAlias

import numpy as np
import numpy.typing as npt

Point3: TypeAlias = tuple[float, float, float]


def xyz_array(points: Sequence[Sequence[float]]) -> npt.NDArray[np.float64]:
    """(N, 3) the points as an array: ``np.asarray(points, dtype=np.float64).reshape(-1, 3)`` at a
    third less cost (numpy does not look at each point as a sequence of its own)."""
    coordinates = itertools.chain.from_iterable(points)
    return np.fromiter(coordinates, dtype=np.float64, count=3 * len(points)).reshape(-1, 3)


def segment_lengths_m(points: Sequence[Point3]) -> list[float]:
    """(N − 1) the 3-D length of each segment of the N points, m: ``np.linalg.norm`` along an
    axis is the square root of ``(dx² + dy²) + dz²``."""
    sqrt = math.sqrt
    lengths_m = []
    for (ax, ay, az), (bx, by, bz) in itertools.pairwise(points):
        dx, dy, dz = bx - ax, by - ay, bz - az
        lengths_m.append(sqrt(dx * dx + dy * dy + dz * dz))
    return lengths_m


def distances_along_m(lengths_m: Sequence[float]) -> list[float]:
    """(N,) the distance of each point of a polyline from its first, m, given the (N − 1) lengths
    of its segments (0 for the first; ``np.cumsum`` adds in order)."""
    return list(itertools.accumulate(lengths_m, initial=0.0))


def point_along(points: Sequence[Point3], walked_m: Sequence[float], along_m: float) -> Point3:
    """The point ``along_m`` along the polyline (N ≥ 2 points whose distances along it are
    ``walked_m``): on the segment where ``np.searchsorted`` puts it (the first or last beyond
    the ends), ``a + t (b − a)`` per coordinate."""
    k = min(max(bisect_left(walked_m, along_m) - 1, 0), len(points) - 2)
    span_m = walked_m[k + 1] - walked_m[k]
    t = 0.0 if span_m == 0 else (along_m - walked_m[k]) / span_m
    (ax, ay, az), (bx, by, bz) = points[k], points[k + 1]
    return (ax + t * (bx - ax), ay + t * (by - ay), az + t * (bz - az))
