"""The path graph's data model: node and edge kinds, :class:`Anchor` and :class:`PathGraph`.

See the package docstring for the attributes of nodes and edges.
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
