"""Floors from height: a walked path spends most of its time on floors and little on stairs.

    levels = find_floor_levels(heights_m)          # e.g. [-5.4, -0.1], lowest first
    floor = assign_floors(heights_m, levels)       # (N,) index into levels, 0 = lowest

A floor level is a height band that holds a sizeable share of the poses; levels closer than
``min_separation_m`` are one floor (ramps, the phone's height changing in the hand).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from app.domain.frames import FloatArray

#: Two levels closer than this are the same floor, m (storeys are ≥ 2.5 m apart).
MIN_FLOOR_SEPARATION_M = 2.0
#: A level needs at least this share of the poses to count as a floor.
MIN_FLOOR_SHARE = 0.05
#: Histogram bin for finding levels, m.
LEVEL_BIN_M = 0.25


def find_floor_levels(
    heights_m: FloatArray,
    *,
    min_separation_m: float = MIN_FLOOR_SEPARATION_M,
    min_share: float = MIN_FLOOR_SHARE,
) -> FloatArray:
    """Heights of the floors the path walks on, m, ascending; one level for a flat path."""
    heights_m = np.asarray(heights_m, dtype=np.float64)
    if heights_m.size == 0:
        return np.empty(0)
    low, high = float(heights_m.min()), float(heights_m.max())
    if high - low < min_separation_m:
        return np.array([float(np.median(heights_m))])
    edges = np.arange(low, high + LEVEL_BIN_M, LEVEL_BIN_M)
    counts, edges = np.histogram(heights_m, bins=edges)
    centres = (edges[:-1] + edges[1:]) / 2
    levels: list[float] = []
    # Greedy: densest bins first, each one a new level unless near an accepted level.
    for b in np.argsort(counts)[::-1]:
        if counts[b] < min_share * heights_m.size:
            break
        if all(abs(centres[b] - level) >= min_separation_m for level in levels):
            levels.append(float(centres[b]))
    refined = []
    for level in sorted(levels):
        near = heights_m[np.abs(heights_m - level) < min_separation_m / 2]
        refined.append(float(np.median(near)))
    return np.array(refined)


def assign_floors(heights_m: FloatArray, levels_m: FloatArray) -> npt.NDArray[np.int64]:
    """(N,) index of the nearest floor level for each height."""
    heights_m = np.asarray(heights_m, dtype=np.float64)
    if len(levels_m) == 0:
        return np.zeros(heights_m.shape, dtype=np.int64)
    distance = np.abs(heights_m[:, None] - np.asarray(levels_m)[None, :])
    return np.asarray(np.argmin(distance, axis=1), dtype=np.int64)
