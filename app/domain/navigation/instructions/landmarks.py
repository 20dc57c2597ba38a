"""Landmarks: the points of interest and tags a step can be told by (:func:`landmark_near`,
within ``LANDMARK_NEAR_M``), made once per graph."""

from __future__ import annotations

import threading
from collections.abc import Sequence
from dataclasses import dataclass

from app.domain.navigation.path_graph import PathGraph
from app.domain.navigation.routing import Point3

#: A tag or point of interest this near a step's place (horizontally, on its floor) is the step's
#: landmark, m: the distance within which a bend is placed at a junction (``JUNCTION_SNAP_M``).
LANDMARK_NEAR_M = 3.0


@dataclass(frozen=True, slots=True, kw_only=True)
class Landmark:
    """A tag or point of interest a step can be told by: ``name`` as said ("Room 210", "tag
    305"), ``position_xz_m`` (map frame, m), ``floor`` (index), ``is_tag``."""

    name: str
    position_xz_m: tuple[float, float]
    floor: int
    is_tag: bool


_LANDMARK_CACHE: dict[int, tuple[PathGraph, list[Landmark]]] = {}
_LANDMARK_CACHE_SIZE = 8
_LANDMARK_LOCK = threading.Lock()


def landmarks_of(pg: PathGraph) -> list[Landmark]:
    """The map's points of interest, then its tags, as landmarks (made once per graph, as
    routing's index is: a graph must not change once routed on)."""
    with _LANDMARK_LOCK:
        cached = _LANDMARK_CACHE.get(id(pg))
    if cached is not None and cached[0] is pg:
        return cached[1]
    found = _landmarks_of(pg)
    with _LANDMARK_LOCK:
        _LANDMARK_CACHE[id(pg)] = (pg, found)
        while len(_LANDMARK_CACHE) > _LANDMARK_CACHE_SIZE:
            del _LANDMARK_CACHE[next(iter(_LANDMARK_CACHE))]
    return found


def _landmarks_of(pg: PathGraph) -> list[Landmark]:
    found = [
        Landmark(
            name=poi.name,
            position_xz_m=(poi.position_m[0], poi.position_m[2]),
            floor=poi.floor,
            is_tag=False,
        )
        for poi in pg.pois
    ]
    found += [
        Landmark(
            name=f"tag {tag_id}",
            position_xz_m=(tag.position_m[0], tag.position_m[2]),
            floor=tag.floor,
            is_tag=True,
        )
        for tag_id, tag in sorted(pg.tags.items())
    ]
    return found


def landmark_near(
    landmarks: Sequence[Landmark], position_m: Point3, floor: int
) -> tuple[str, str] | None:
    """(name, phrase) of the landmark of a step at ``position_m`` on ``floor``: the nearest point
    of interest within ``LANDMARK_NEAR_M`` (horizontally, on that floor), "at the tag by Room
    210" when a tag is that near too, else "by Room 210"; else the nearest tag, "at tag 305";
    else None. Ties go to the first listed (points of interest, then tags by id)."""
    x, _, z = position_m
    near_m2 = LANDMARK_NEAR_M * LANDMARK_NEAR_M
    poi: tuple[float, str] | None = None
    tag: tuple[float, str] | None = None
    for landmark in landmarks:  # squared distances: the same order, no square roots
        if landmark.floor != floor:
            continue
        dx, dz = landmark.position_xz_m[0] - x, landmark.position_xz_m[1] - z
        d_m2 = dx * dx + dz * dz
        if d_m2 > near_m2:
            continue
        if landmark.is_tag:
            if tag is None or d_m2 < tag[0]:
                tag = (d_m2, landmark.name)
        elif poi is None or d_m2 < poi[0]:
            poi = (d_m2, landmark.name)
    if poi is not None:
        return poi[1], (f"at the tag by {poi[1]}" if tag is not None else f"by {poi[1]}")
    if tag is not None:
        return tag[1], f"at {tag[1]}"
    return None
