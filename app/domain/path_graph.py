"""The path graph: where a pedestrian can walk in a map — the walked path, with junctions where it
crosses itself, floors, and stairs/elevators where it changes floor.

Data model (the builder and the serializers are filled in below this block):

- ``graph``: an undirected ``networkx.Graph`` with integer node ids.
  Node attributes: ``position_m`` (x, y, z) in the map frame (y up), ``floor`` (int, 0 = lowest),
  ``kind`` (``"node"`` for a kept pose, ``"junction"`` for a crossing), ``pose_index`` (int, the
  row of the pose in the map's trajectory; None for junctions).
  Edge attributes: ``length_m`` (3-D length, m), ``kind`` (``"walk"``, ``"stairs"`` or
  ``"elevator"``), ``floor`` (the floor of a walk edge; for a floor change, the lower floor).
- ``floor_levels_m``: height of each floor, m, lowest first (``app.domain.floors``).
- ``tags``: tag id → :class:`Anchor` (the node the tag is reached from).
- ``pois``: the points of interest, each an :class:`Anchor` with its name.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import networkx as nx

NODE = "node"
JUNCTION = "junction"
WALK = "walk"
STAIRS = "stairs"
ELEVATOR = "elevator"
EDGE_KINDS = (WALK, STAIRS, ELEVATOR)


@dataclass(frozen=True, slots=True, kw_only=True)
class Anchor:
    """A tag or point of interest and the graph node it is reached from.

    position_m: where the thing itself is (map frame, m); ``node``: its nearest reachable node.
    """

    name: str
    node: int
    position_m: tuple[float, float, float]
    floor: int


@dataclass(frozen=True, slots=True, kw_only=True)
class PathGraph:
    """A map version's path graph (see the module docstring for the attributes)."""

    graph: nx.Graph[int] = field(default_factory=nx.Graph)
    floor_levels_m: tuple[float, ...] = ()
    tags: dict[int, Anchor] = field(default_factory=dict)
    pois: tuple[Anchor, ...] = ()
