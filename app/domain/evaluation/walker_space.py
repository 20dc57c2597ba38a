"""The true building a simulated walker walks (``app.domain.evaluation.walker``): where it can be.

BoxFreeSpace.of_building(walk.building)                # a simulated building's truth
CapsuleFreeSpace.of_lines(lines_xz, radius_m=1.6)      # corridors drawn as centrelines
space.contains(points_xz, floor)                       # (N,) bool
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import numpy.typing as npt

from app.domain.frames import FloatArray

BoolArray = npt.NDArray[np.bool_]


class FreeSpace(Protocol):
    """Where a walker can be: ``contains(xz, floor)`` → (N,) bool for points (N, 2), m."""

    def contains(self, xz: FloatArray, floor: int) -> BoolArray: ...


@dataclass(frozen=True, slots=True, eq=False)
class BoxFreeSpace:
    """The free space of a simulated building: axis-aligned boxes (B, 2, 3) of min and max
    corners (y up), each on the floor whose level its bottom is nearest; ``stairs`` the stairs'
    centrelines (P, 3), each from its lower end."""

    boxes_m: FloatArray
    floor_levels_m: tuple[float, ...]
    stairs: tuple[FloatArray, ...] = ()
    _on_floor: BoolArray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        levels = np.asarray(self.floor_levels_m, dtype=np.float64)
        bottoms, tops = self.boxes_m[:, 0, 1], self.boxes_m[:, 1, 1]
        # (B, F): a box is on every floor whose level lies within it (a stairwell spans two)
        on_floor = (bottoms[:, None] - 0.5 <= levels[None, :]) & (levels[None, :] < tops[:, None])
        object.__setattr__(self, "_on_floor", on_floor)

    @classmethod
    def of_building(cls, building: object) -> BoxFreeSpace:
        """The truth of an ``app.domain.evaluation.simulate.Building``."""
        boxes = np.asarray(building.free_space_boxes_m, dtype=np.float64)  # type: ignore[attr-defined]
        ends = np.asarray(building.edge_nodes)  # type: ignore[attr-defined]
        xyz = np.asarray(building.node_xyz_m)  # type: ignore[attr-defined]
        polylines = building.edge_polylines_m  # type: ignore[attr-defined]
        stairs = tuple(
            np.asarray(polylines[e], dtype=np.float64)
            for e in range(len(ends))
            if abs(float(xyz[ends[e, 0], 1] - xyz[ends[e, 1], 1])) > 1e-9
        )
        levels = tuple(float(v) for v in building.floor_heights_m)  # type: ignore[attr-defined]
        return cls(boxes, levels, stairs)

    def contains(self, xz: FloatArray, floor: int) -> BoolArray:
        on = self._on_floor[:, floor]
        low, high = self.boxes_m[on, 0][:, [0, 2]], self.boxes_m[on, 1][:, [0, 2]]
        p = xz[:, None, :]
        return np.asarray(((p >= low[None]) & (p <= high[None])).all(axis=2).any(axis=1))


@dataclass(frozen=True, slots=True, eq=False)
class CapsuleFreeSpace:
    """Corridors drawn as centrelines: segments (S, 2, 2) (x–z, m) widened by ``radius_m``, one
    floor (floor 0)."""

    segments_m: FloatArray
    radius_m: float

    @classmethod
    def of_lines(
        cls, lines_xz: Sequence[Sequence[tuple[float, float]]], *, radius_m: float
    ) -> CapsuleFreeSpace:
        segments = [(a, b) for line in lines_xz for a, b in itertools.pairwise(line)]
        return cls(np.asarray(segments, dtype=np.float64).reshape(-1, 2, 2), radius_m)

    def contains(self, xz: FloatArray, floor: int) -> BoolArray:
        if floor != 0:
            return np.zeros(len(xz), dtype=np.bool_)
        a, b = self.segments_m[:, 0], self.segments_m[:, 1]
        ab = b - a
        ap = xz[:, None, :] - a[None]
        t = np.clip((ap * ab).sum(axis=2) / np.maximum((ab * ab).sum(axis=1), 1e-12), 0.0, 1.0)
        distance = np.linalg.norm(ap - t[..., None] * ab, axis=2).min(axis=1)
        return np.asarray(distance <= self.radius_m)


def clear_line(space: FreeSpace, a_xz: FloatArray, b_xz: FloatArray, floor: int) -> bool:
    """Whether the segment between two points (2,) (x–z, m) lies in the free space of ``floor``
    (sampled every 0.1 m): nothing stands between them."""
    length_m = float(np.linalg.norm(b_xz - a_xz))
    t = np.linspace(0.0, 1.0, max(2, int(length_m / 0.1) + 1))
    points = a_xz[None, :] + t[:, None] * (b_xz - a_xz)[None, :]
    return bool(space.contains(points, floor).all())
