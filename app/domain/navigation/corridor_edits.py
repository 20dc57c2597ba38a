"""Corridor edits (issue 27): an operator's corrections of a map's corridor graph, kept as data in
the map's frame and applied to every version of the map.

    edit = edit_from_json({"op": "quiet", "at": [12.0, 0.1, -3.5]})    # EditInvalid naming a field
    edited = apply_edits(pg, [edit, …])          # never raises: each edit applied or reported
    edited.path_graph, edited.outcomes[0].applied, edited.outcomes[0].reason
    after = apply_new_edit_to(edited, edit)      # a new edit: applies exactly, or raises
    later = apply_more_edits(edited, [edit, …])  # edits added since: as apply_edits would

**Operations** (the names and fields are a contract of the API; points ``[x, y, z]`` in the map
frame, m, y up):

==============  ===================================  =============================================
``op``          fields                               what it does
==============  ===================================  =============================================
``quiet``       ``at``                               no decision is announced at the node at ``at``
``add_edge``    ``from``, ``to``, ``kind``           a corridor (``walk``), a ``door``, ``stairs``
                                                     or an ``elevator`` between two places
``remove_edge`` ``from``, ``to``                     the corridor between two places is removed
``move_node``   ``from``, ``to``                     the node at ``from`` is moved to ``to``
``add_poi``     ``name``, ``at``                     a point of interest at ``at``
``rename_poi``  ``name``, ``new_name`` [, ``at``]    the point of interest ``name`` is renamed
``remove_poi``  ``name`` [, ``at``]                  the point of interest ``name`` is removed
==============  ===================================  =============================================

**Anchoring.** Node ids do not survive a rebuild, so an edit names places, and each place is
found again on every graph it is applied to: its floor is the floor level nearest its height
(within ``FLOOR_TOLERANCE_M``), and on that floor the nearest node within ``NODE_TOLERANCE_M``
(horizontal distance). The ends of ``add_edge`` may also land on a corridor: without a node that
near, the nearest point of a walk edge within ``NODE_TOLERANCE_M`` splits that edge. A
``remove_edge`` removes the edge between the two nodes found, or the run of edges joining them
that stays within ``NODE_TOLERANCE_M`` of the segment between the two places (a rebuild may have
put a node in the middle of what was one edge). Points of interest are found by name (the
nearest of that name to ``at`` when given, within ``POI_TOLERANCE_M``); a new one is attached to
the nearest point of a corridor of its floor, as the skeleton attaches them.

**Checks.** A point whose height is on no floor, or that lies more than ``MAP_MARGIN_M`` outside
the map (the extent of its nodes, tags and points of interest), is refused naming the field; so
is an edge from a node to itself, a walk or door between two floors, stairs or an elevator within
one, a duplicate of an existing edge, and a ``remove_edge`` that would cut a tag or a point of
interest off from the rest of the map (the app traps on an unreachable destination).

**Applying.** :func:`apply_edits` applies the edits in order to a copy of the graph, each one
whole or not at all; one that finds no anchor or would break a check is kept out and reported
with its reason (:class:`EditOutcome`), never dropped silently. :func:`apply_new_edit` is the
strict form for a new edit: it raises :class:`EditInvalid` (a bad request, naming the field) or
:class:`EditConflict` (the graph's state forbids it), so that nothing is stored that does not apply
to the current version. :func:`apply_new_edit_to` (strict) and :func:`apply_more_edits` continue
an :class:`EditedGraph` (with the unedited graph's extent and the next new node's id), so an edit
costs the same with 10 or 10,000 before it, and what they make is what :func:`apply_edits` makes
of all the edits from scratch (the same node ids, the same outcomes). A door is a walk edge with
``door`` True (routing walks through it); a quiet node has ``quiet`` True and is in the graph
attribute ``quiet_nodes``, which :mod:`app.domain.navigation.instructions` honours. Nodes an edit
adds get new ids above the largest, kind ``node`` and no ``pose_index``; a node where three or
more corridors meet after an edit becomes a ``junction``.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any, Final, cast

import networkx as nx
import numpy as np
import numpy.typing as npt

from app.domain.errors import InvisibleMapError
from app.domain.frames import FloatArray
from app.domain.mapping.map_result import MapResult
from app.domain.navigation.path_graph import (
    ELEVATOR,
    JUNCTION,
    NODE,
    STAIRS,
    WALK,
    Anchor,
    PathGraph,
)

Point3 = tuple[float, float, float]

QUIET: Final = "quiet"
ADD_EDGE: Final = "add_edge"
REMOVE_EDGE: Final = "remove_edge"
MOVE_NODE: Final = "move_node"
ADD_POI: Final = "add_poi"
RENAME_POI: Final = "rename_poi"
REMOVE_POI: Final = "remove_poi"
#: Every operation, and the fields each takes (required, optional).
OP_FIELDS: Final[dict[str, tuple[tuple[str, ...], tuple[str, ...]]]] = {
    QUIET: (("at",), ()),
    ADD_EDGE: (("from", "to", "kind"), ()),
    REMOVE_EDGE: (("from", "to"), ()),
    MOVE_NODE: (("from", "to"), ()),
    ADD_POI: (("name", "at"), ()),
    RENAME_POI: (("name", "new_name"), ("at",)),
    REMOVE_POI: (("name",), ("at",)),
}
OPS: Final = tuple(OP_FIELDS)
#: A door: a walk edge (routes go through it) marked ``door``.
DOOR: Final = "door"
#: The kinds an added edge may have.
ADD_EDGE_KINDS: Final = (WALK, DOOR, STAIRS, ELEVATOR)

#: A place names the node within this horizontal distance of it (the nearest), m. Chosen in
#: docs/navigation.md "Corridor edits": skeleton nodes move by up to ~0.9 m between versions of a
#: corridor; 1.5 m keeps two nodes a corridor width (1.8 m) apart distinct.
NODE_TOLERANCE_M = 1.5
#: A point is on the floor whose level is nearest its height if it is within this of it, m
#: (storeys are at least 2.5 m apart; tags hang up to ~1 m above the phone's height).
FLOOR_TOLERANCE_M = 1.5
#: A point farther than this outside the map's extent is refused, m.
MAP_MARGIN_M = 20.0
#: A point of interest named with ``at`` is the one of that name nearest ``at`` within this, m.
POI_TOLERANCE_M = 5.0
#: Longest name of a point of interest, characters.
MAX_NAME_LENGTH = 200
#: Two positions closer than this are one point of interest's, m (the path graph keeps the
#: map's positions as floats: they are equal).
SAME_POSITION_M = 1e-6
#: The graph attribute (``PathGraph.graph.graph``) holding the quiet nodes.
QUIET_NODES: Final = "quiet_nodes"


class EditError(InvisibleMapError):
    """Base of the errors of an edit; ``field`` names the part of it at fault ("" for the whole)."""

    def __init__(self, field: str, reason: str) -> None:
        self.field = field
        self.reason = reason
        super().__init__(f"{field}: {reason}" if field else reason)


class EditInvalid(EditError):
    """Raised when an edit is malformed or names a place that is not in the map (a 422): an
    unknown op or field, a point far outside the map or on no floor, a self-loop, no anchor."""


class EditConflict(EditError):
    """Raised when a well-formed edit cannot apply to the graph as it is (a 409): a duplicate
    edge, a removal that cuts a tag or point of interest off, a name already taken."""


@dataclass(frozen=True, slots=True, kw_only=True)
class CorridorEdit:
    """One edit (see the module docstring); the fields its ``op`` does not take are None."""

    op: str
    at_m: Point3 | None = None
    from_m: Point3 | None = None
    to_m: Point3 | None = None
    kind: str | None = None
    name: str | None = None
    new_name: str | None = None

    def to_json(self) -> dict[str, Any]:
        """The edit as the API writes it: ``op`` and its fields only, points as lists."""
        values = {
            "at": self.at_m,
            "from": self.from_m,
            "to": self.to_m,
            "kind": self.kind,
            "name": self.name,
            "new_name": self.new_name,
        }
        document: dict[str, Any] = {"op": self.op}
        for name, value in values.items():
            if value is not None:
                document[name] = list(value) if isinstance(value, tuple) else value
        return document


@dataclass(frozen=True, slots=True, kw_only=True)
class EditOutcome:
    """What became of one edit on one graph: ``applied``, else ``reason`` (one line) and the
    ``field`` whose place was not found or is at fault."""

    applied: bool
    reason: str | None = None
    field: str | None = None


@dataclass(frozen=True, slots=True, kw_only=True)
class EditedGraph:
    """A path graph with edits applied: the edited graph and one outcome per edit, in order;
    ``extent`` (the unedited graph's: min x, max x, min z, max z, m) and ``next_id`` (the id
    the next node an edit adds gets) let more edits continue it exactly as :func:`apply_edits`
    would (None: those of ``path_graph`` itself, a graph no edit touched)."""

    path_graph: PathGraph
    outcomes: tuple[EditOutcome, ...]
    extent: tuple[float, float, float, float] | None = None
    next_id: int | None = None

    @property
    def applied_count(self) -> int:
        return sum(1 for outcome in self.outcomes if outcome.applied)


# --------------------------------------------------------------------------- reading an edit


def edit_from_json(document: Any) -> CorridorEdit:
    """An edit from its JSON form; EditInvalid naming the first field at fault (``op``, ``at``,
    ``from``, ``to``, ``kind``, ``name``, ``new_name``, or an unknown field's name)."""
    if not isinstance(document, Mapping):
        raise EditInvalid("", "an edit is a JSON object with an 'op'")
    op = document.get("op")
    if not isinstance(op, str) or op not in OP_FIELDS:
        raise EditInvalid("op", f"unknown op {op!r}: one of {', '.join(OPS)}")
    required, optional = OP_FIELDS[op]
    for name in document:
        if name != "op" and name not in required and name not in optional:
            raise EditInvalid(
                str(name), f"{op} takes no field {name!r} (it takes {', '.join(required)})"
            )
    for name in required:
        if document.get(name) is None:
            raise EditInvalid(name, f"{op} needs {name!r}")
    values: dict[str, Any] = {}
    for name, attribute in (("at", "at_m"), ("from", "from_m"), ("to", "to_m")):
        if document.get(name) is not None:
            values[attribute] = _point(document[name], name)
    for name in ("name", "new_name"):
        if document.get(name) is not None:
            values[name] = _name(document[name], name)
    if op == ADD_EDGE:
        kind = document["kind"]
        if kind not in ADD_EDGE_KINDS:
            raise EditInvalid("kind", f"unknown kind {kind!r}: one of {', '.join(ADD_EDGE_KINDS)}")
        values["kind"] = kind
    return CorridorEdit(op=op, **values)


def _point(value: Any, field: str) -> Point3:
    if (
        not isinstance(value, list | tuple)
        or len(value) != 3
        or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)
    ):
        raise EditInvalid(field, "a point is [x, y, z]: three numbers, m, map frame")
    try:
        x, y, z = (float(v) for v in value)
    except OverflowError as err:  # an int of hundreds of digits
        raise EditInvalid(field, "a point's coordinates must be finite numbers") from err
    if not all(math.isfinite(v) for v in (x, y, z)):
        raise EditInvalid(field, "a point's coordinates must be finite numbers")
    return (x, y, z)


def _name(value: Any, field: str) -> str:
    if not isinstance(value, str) or not value.strip():
        raise EditInvalid(field, "a name is a non-empty string")
    name = value.strip()
    if len(name) > MAX_NAME_LENGTH:
        raise EditInvalid(field, f"a name is at most {MAX_NAME_LENGTH} characters ({len(name)})")
    return name


# --------------------------------------------------------------------------- applying


def apply_edits(pg: PathGraph, edits: Sequence[CorridorEdit]) -> EditedGraph:
    """``pg`` with ``edits`` applied in order (``pg`` is not changed): each edit whole or not at
    all; an edit that finds no anchor, or would break a check, is left out and its outcome says
    why. Without edits, ``pg`` itself."""
    return apply_more_edits(EditedGraph(path_graph=pg, outcomes=()), edits)


def apply_more_edits(edited: EditedGraph, edits: Sequence[CorridorEdit]) -> EditedGraph:
    """``edited`` with ``edits`` (made after its own) applied in order, as :func:`apply_edits`
    applies them (``edited`` is not changed): ``apply_more_edits(apply_edits(pg, a), b)`` is
    ``apply_edits(pg, [*a, *b])``, at the cost of ``b`` alone."""
    if not edits:
        return edited
    work = _Work.of(edited.path_graph, extent=edited.extent, next_id=edited.next_id)
    outcomes = list(edited.outcomes)
    for edit in edits:
        try:
            work.apply(edit, new=False)
        except EditError as err:
            outcomes.append(EditOutcome(applied=False, reason=err.reason, field=err.field or None))
        else:
            outcomes.append(EditOutcome(applied=True))
    return work.edited(tuple(outcomes))


def apply_new_edit(pg: PathGraph, edit: CorridorEdit) -> PathGraph:
    """``pg`` with a new ``edit`` applied (``pg`` is not changed); EditInvalid or EditConflict
    if it cannot apply exactly (stricter than :func:`apply_edits`: a node quiet already, or a
    point of interest named already, is a conflict here). :func:`apply_new_edit_to` continues
    an edited graph."""
    return apply_new_edit_to(EditedGraph(path_graph=pg, outcomes=()), edit).path_graph


def apply_new_edit_to(edited: EditedGraph, edit: CorridorEdit) -> EditedGraph:
    """``edited`` with a new ``edit`` applied, its outcome ``applied`` (``edited`` is not
    changed); EditInvalid or EditConflict as :func:`apply_new_edit`. What it makes is what
    :func:`apply_edits` makes of the edits before and this one, at the cost of this one."""
    work = _Work.of(edited.path_graph, extent=edited.extent, next_id=edited.next_id)
    work.apply(edit, new=True)
    return work.edited((*edited.outcomes, EditOutcome(applied=True)))


def quiet_nodes(pg: PathGraph) -> frozenset[int]:
    """The nodes at which no decision is announced."""
    nodes: frozenset[int] = pg.graph.graph.get(QUIET_NODES, frozenset())
    return nodes


@dataclass(slots=True)
class _Work:
    """The graph being edited: a copy of the graph, the tags and the points of interest."""

    G: nx.Graph[int]
    floor_levels_m: tuple[float, ...]
    tags: dict[int, Anchor]
    pois: list[Anchor]
    poi_names: dict[str, int]  # how many points of interest have each name
    extent: tuple[float, float, float, float]  # min x, max x, min z, max z, m
    next_id: int
    # the nodes as arrays, for finding the nearest (a removed node's floor is −1)
    node_ids: list[int]
    node_xz: FloatArray  # (N, 2) m
    node_floor: npt.NDArray[np.int64]  # (N,)
    row_of: dict[int, int]

    @classmethod
    def of(
        cls,
        pg: PathGraph,
        *,
        extent: tuple[float, float, float, float] | None = None,
        next_id: int | None = None,
    ) -> _Work:
        """A copy of ``pg`` to edit; ``extent`` and ``next_id`` those of an edited graph being
        continued (None: ``pg``'s own)."""
        G = pg.graph.copy()
        if extent is None:
            xs, zs = [], []
            for _, d in G.nodes(data=True):
                xs.append(d["position_m"][0])
                zs.append(d["position_m"][2])
            for anchor in (*pg.tags.values(), *pg.pois):
                xs.append(anchor.position_m[0])
                zs.append(anchor.position_m[2])
            extent = (min(xs), max(xs), min(zs), max(zs)) if xs else (0.0, 0.0, 0.0, 0.0)
        node_ids = [int(n) for n in G.nodes]
        positions = [G.nodes[n]["position_m"] for n in node_ids]
        poi_names: dict[str, int] = {}
        for poi in pg.pois:
            poi_names[poi.name] = poi_names.get(poi.name, 0) + 1
        return cls(
            G=G,
            floor_levels_m=tuple(pg.floor_levels_m),
            tags=dict(pg.tags),
            pois=list(pg.pois),
            poi_names=poi_names,
            extent=extent,
            next_id=max(node_ids, default=-1) + 1 if next_id is None else next_id,
            node_ids=node_ids,
            node_xz=np.array([(p[0], p[2]) for p in positions], dtype=np.float64).reshape(-1, 2),
            node_floor=np.array([G.nodes[n]["floor"] for n in node_ids], dtype=np.int64),
            row_of={n: k for k, n in enumerate(node_ids)},
        )

    def _indexed(self, node: int) -> None:
        """Note the node's position and floor (added or moved) in the arrays."""
        d = self.G.nodes[node]
        row = self.row_of.get(node)
        if row is None:
            row = len(self.node_ids)
            self.row_of[node] = row
            self.node_ids.append(node)
            self.node_xz = np.vstack([self.node_xz, np.zeros((1, 2))])
            self.node_floor = np.append(self.node_floor, 0)
        self.node_xz[row] = (d["position_m"][0], d["position_m"][2])
        self.node_floor[row] = d["floor"]

    def _remove_node(self, node: int) -> None:
        self.G.remove_node(node)
        self.node_floor[self.row_of[node]] = -1

    def path_graph(self) -> PathGraph:
        self.G.graph[QUIET_NODES] = frozenset(
            n for n, quiet in self.G.nodes(data="quiet", default=False) if quiet
        )
        return PathGraph(
            graph=self.G,
            floor_levels_m=self.floor_levels_m,
            tags=dict(self.tags),
            pois=tuple(self.pois),
        )

    def edited(self, outcomes: tuple[EditOutcome, ...]) -> EditedGraph:
        """The graph as edited, with ``outcomes``, to be continued by more edits."""
        return EditedGraph(
            path_graph=self.path_graph(),
            outcomes=outcomes,
            extent=self.extent,
            next_id=self.next_id,
        )

    # ------------------------------------------------------------------ the operations

    def apply(self, edit: CorridorEdit, *, new: bool) -> None:
        """Apply ``edit`` whole, or raise EditError having changed nothing."""
        if self.G.number_of_nodes() == 0:
            raise EditInvalid("", "the map's corridor graph is empty")
        match edit.op:
            case "quiet":
                self._quiet(_given(edit.at_m), new=new)
            case "add_edge":
                self._add_edge(_given(edit.from_m), _given(edit.to_m), edit.kind or WALK)
            case "remove_edge":
                self._remove_edge(_given(edit.from_m), _given(edit.to_m))
            case "move_node":
                self._move_node(_given(edit.from_m), _given(edit.to_m))
            case "add_poi":
                self._add_poi(edit.name or "", _given(edit.at_m))
            case "rename_poi":
                self._rename_poi(edit.name or "", edit.new_name or "", edit.at_m, new=new)
            case "remove_poi":
                self._remove_poi(edit.name or "", edit.at_m)
            case _:
                raise EditInvalid("op", f"unknown op {edit.op!r}: one of {', '.join(OPS)}")

    def _quiet(self, at_m: Point3, *, new: bool) -> None:
        floor = self._floor(at_m, "at")
        node = self._node_near(at_m, floor, "at")
        if self.G.nodes[node].get("quiet"):
            if new:
                raise EditConflict("at", f"node {node} at {_shown(at_m)} is quiet already")
            return
        self.G.nodes[node]["quiet"] = True

    def _add_edge(self, from_m: Point3, to_m: Point3, kind: str) -> None:
        floor_a, floor_b = self._floor(from_m, "from"), self._floor(to_m, "to")
        if kind in (WALK, DOOR) and floor_a != floor_b:
            raise EditInvalid(
                "to",
                f"a {kind} joins two places of one floor: 'from' is on floor {floor_a + 1}, "
                f"'to' on floor {floor_b + 1} (use stairs or elevator)",
            )
        if kind in (STAIRS, ELEVATOR) and floor_a == floor_b:
            raise EditInvalid(
                "to", f"{kind} join two floors: 'from' and 'to' are both on floor {floor_a + 1}"
            )
        undo: list[tuple[int, int, int, dict[str, Any]]] = []  # the edges split, to undo
        try:
            u = self._node_or_corridor(from_m, floor_a, "from", undo)
            v = self._node_or_corridor(to_m, floor_b, "to", undo)
            if u == v:
                raise EditInvalid(
                    "to", f"'from' and 'to' are the same node ({u}): an edge needs two"
                )
            if self.G.has_edge(u, v):
                raise EditConflict(
                    "to", f"the edge {u}–{v} exists already ({self._edge_kind(u, v)})"
                )
            if floor_a == floor_b and self._run_between(u, v, self._position(u), self._position(v)):
                raise EditConflict("to", f"a corridor from {u} to {v} exists already")
        except EditError:
            for node, a, b, data in reversed(undo):
                self._remove_node(node)
                self.G.add_edge(a, b, **data)
                self.next_id -= 1
            raise
        attributes: dict[str, Any] = {
            "length_m": _distance_3d(self._position(u), self._position(v)),
            "kind": WALK if kind == DOOR else kind,
            "floor": min(floor_a, floor_b),
        }
        if kind == DOOR:
            attributes["door"] = True
        self.G.add_edge(u, v, **attributes)
        for node in (u, v):
            self._update_kind(node)

    def _remove_edge(self, from_m: Point3, to_m: Point3) -> None:
        floor_a, floor_b = self._floor(from_m, "from"), self._floor(to_m, "to")
        u = self._node_near(from_m, floor_a, "from")
        v = self._node_near(to_m, floor_b, "to")
        if u == v:
            raise EditInvalid("to", f"'from' and 'to' are the same node ({u}): an edge needs two")
        run = [(u, v)] if self.G.has_edge(u, v) else self._run_between(u, v, from_m, to_m)
        if not run:
            raise EditInvalid(
                "to", f"no edge joins the nodes at {_shown(from_m)} ({u}) and {_shown(to_m)} ({v})"
            )
        removed = [(a, b, dict(self.G.edges[a, b])) for a, b in run]
        self.G.remove_edges_from(run)
        cut = self._cut_off(u, v, [a for a, _ in run[1:]])
        if cut is not None:
            self.G.add_edges_from(removed)
            raise EditConflict(
                "to",
                f"removing the edge {u}–{v} would cut {cut} off from the rest of the map "
                "(the app cannot route to a place it cannot reach)",
            )
        for node in dict.fromkeys(a for a, _ in run[1:]):  # interior nodes left with no edge go
            if self.G.degree(node) == 0 and not self._anchors(node):
                self._remove_node(node)
        for node in (u, v):
            self._update_kind(node)

    def _move_node(self, from_m: Point3, to_m: Point3) -> None:
        floor = self._floor(from_m, "from")
        node = self._node_near(from_m, floor, "from")
        floor_to = self._floor(to_m, "to")
        if floor_to != floor:
            raise EditInvalid(
                "to",
                f"a node moves within its floor: 'from' is on floor {floor + 1}, "
                f"'to' on floor {floor_to + 1}",
            )
        y = self._position(node)[1]
        position = (to_m[0], y, to_m[2])  # the node keeps its height (its floor's level)
        self.G.nodes[node]["position_m"] = position
        self._indexed(node)
        for other in self.G.neighbors(node):
            self.G.edges[node, other]["length_m"] = _distance_3d(position, self._position(other))

    def _add_poi(self, name: str, at_m: Point3) -> None:
        floor = self._floor(at_m, "at")
        if self.poi_names.get(name, 0):
            raise EditConflict("name", f"a point of interest named {name!r} exists already")
        node = self._attach(at_m, floor)
        self.pois.append(Anchor(name=name, node=node, position_m=at_m, floor=floor))
        self._named(name, +1)

    def _rename_poi(self, name: str, new_name: str, at_m: Point3 | None, *, new: bool) -> None:
        k = self._poi(name, at_m)
        if new_name == name:
            if new:
                raise EditInvalid("new_name", f"the point of interest is named {name!r} already")
            return
        if self.poi_names.get(new_name, 0):  # not the one renamed: its name is another
            raise EditConflict("new_name", f"a point of interest named {new_name!r} exists already")
        self.pois[k] = replace(self.pois[k], name=new_name)
        self._named(name, -1)
        self._named(new_name, +1)

    def _remove_poi(self, name: str, at_m: Point3 | None) -> None:
        del self.pois[self._poi(name, at_m)]
        self._named(name, -1)

    def _named(self, name: str, change: int) -> None:
        count = self.poi_names.get(name, 0) + change
        if count:
            self.poi_names[name] = count
        else:
            self.poi_names.pop(name, None)

    # ------------------------------------------------------------------ finding places

    def _floor(self, point_m: Point3, field: str) -> int:
        """The floor of ``point_m`` (EditInvalid naming ``field`` when it is on none, or far
        outside the map)."""
        min_x, max_x, min_z, max_z = self.extent
        outside_m = max(
            min_x - point_m[0], point_m[0] - max_x, min_z - point_m[2], point_m[2] - max_z
        )
        if outside_m > MAP_MARGIN_M:
            raise EditInvalid(
                field,
                f"{_shown(point_m)} is {outside_m:.0f} m outside the map (x {min_x:.1f} to "
                f"{max_x:.1f} m, z {min_z:.1f} to {max_z:.1f} m; at most {MAP_MARGIN_M:.0f} m "
                "outside)",
            )
        levels = self.floor_levels_m
        if not levels:
            return 0
        floor = min(range(len(levels)), key=lambda f: abs(levels[f] - point_m[1]))
        if abs(levels[floor] - point_m[1]) > FLOOR_TOLERANCE_M:
            shown = ", ".join(f"{level:.2f}" for level in levels)
            raise EditInvalid(
                field,
                f"height y = {point_m[1]:.2f} m is on no floor of this map (floors at {shown} m, "
                f"within {FLOOR_TOLERANCE_M} m)",
            )
        return floor

    def _node_near(self, point_m: Point3, floor: int, field: str) -> int:
        """The node of ``floor`` nearest ``point_m`` within NODE_TOLERANCE_M (EditInvalid)."""
        node, distance_m = self._nearest_node(point_m, floor)
        if node is None or distance_m > NODE_TOLERANCE_M:
            nearest = "" if node is None else f" (the nearest is {distance_m:.1f} m away)"
            raise EditInvalid(
                field,
                f"no node within {NODE_TOLERANCE_M} m of {_shown(point_m)} on floor {floor + 1}"
                f"{nearest}",
            )
        return node

    def _nearest_node(self, point_m: Point3, floor: int) -> tuple[int | None, float]:
        rows = np.flatnonzero(self.node_floor == floor)
        if len(rows) == 0:
            return None, math.inf
        offsets = self.node_xz[rows] - (point_m[0], point_m[2])
        squared = np.einsum("ij,ij->i", offsets, offsets)
        k = int(np.argmin(squared))
        return self.node_ids[int(rows[k])], math.sqrt(float(squared[k]))

    def _nearest_walk_point(
        self, point_m: Point3, floor: int
    ) -> tuple[tuple[int, int, float] | None, float]:
        """((u, v, t), horizontal distance) of the nearest point of a walk edge of ``floor``:
        u + t (v − u), t in [0, 1]."""
        best: tuple[int, int, float] | None = None
        best_m = math.inf
        px, pz = point_m[0], point_m[2]
        nodes = self.G.nodes
        for u, v, d in self.G.edges(data=True):
            if d["kind"] != WALK or d["floor"] != floor:
                continue
            a, b = nodes[u]["position_m"], nodes[v]["position_m"]
            if (  # the edge's box is farther than the best so far: it cannot be nearer
                px - max(a[0], b[0]) > best_m
                or min(a[0], b[0]) - px > best_m
                or pz - max(a[2], b[2]) > best_m
                or min(a[2], b[2]) - pz > best_m
            ):
                continue
            t, distance_m = _projection_xz(point_m, a, b)
            if distance_m < best_m:
                best, best_m = (int(u), int(v), t), distance_m
        return best, best_m

    def _node_or_corridor(
        self,
        point_m: Point3,
        floor: int,
        field: str,
        undo: list[tuple[int, int, int, dict[str, Any]]],
    ) -> int:
        """The node near ``point_m``, else a new node splitting the walk edge near it (noted in
        ``undo`` as (new node, u, v, the edge's attributes)); EditInvalid when neither is within
        NODE_TOLERANCE_M."""
        node, node_m = self._nearest_node(point_m, floor)
        if node is not None and node_m <= NODE_TOLERANCE_M:
            return node
        on_edge, edge_m = self._nearest_walk_point(point_m, floor)
        if on_edge is None or edge_m > NODE_TOLERANCE_M:
            raise EditInvalid(
                field,
                f"no node or corridor within {NODE_TOLERANCE_M} m of {_shown(point_m)} on floor "
                f"{floor + 1}",
            )
        u, v, t = on_edge
        data = dict(self.G.edges[u, v])
        split = self._split(u, v, t)
        undo.append((split, u, v, data))
        return split

    def _attach(self, point_m: Point3, floor: int) -> int:
        """The node a new point of interest at ``point_m`` is reached from: the nearest point of
        a walk edge of its floor (the edge split there unless a node is within NODE_TOLERANCE_M
        of it), else the nearest node of the floor."""
        on_edge, _ = self._nearest_walk_point(point_m, floor)
        if on_edge is None:
            node, _ = self._nearest_node(point_m, floor)
            if node is None:
                raise EditInvalid("at", f"floor {floor + 1} has no corridor to reach it from")
            return node
        u, v, t = on_edge
        here = _lerp(self._position(u), self._position(v), t)
        for end in (u, v):
            if _distance_xz(here, self._position(end)) <= NODE_TOLERANCE_M:
                return end
        return self._split(u, v, t)

    def _split(self, u: int, v: int, t: float) -> int:
        """A new node on the edge u–v at u + t (v − u), the edge replaced by its two parts."""
        data = dict(self.G.edges[u, v])
        a, b = self._position(u), self._position(v)
        here = _lerp(a, b, t)
        node = self.next_id
        self.next_id += 1
        self.G.add_node(
            node, position_m=here, floor=int(self.G.nodes[u]["floor"]), kind=NODE, pose_index=None
        )
        self._indexed(node)
        self.G.remove_edge(u, v)
        self.G.add_edge(u, node, **{**data, "length_m": _distance_3d(a, here)})
        self.G.add_edge(node, v, **{**data, "length_m": _distance_3d(here, b)})
        return node

    def _run_between(self, u: int, v: int, from_m: Point3, to_m: Point3) -> list[tuple[int, int]]:
        """The edges of the shortest run from u to v through nodes within NODE_TOLERANCE_M of
        the segment from ``from_m`` to ``to_m`` (horizontal) where no other corridor branches
        off (each of degree 2), or [] if there is none: one corridor that a rebuild or an edit
        split into several edges."""
        low_x = min(from_m[0], to_m[0]) - NODE_TOLERANCE_M
        high_x = max(from_m[0], to_m[0]) + NODE_TOLERANCE_M
        low_z = min(from_m[2], to_m[2]) - NODE_TOLERANCE_M
        high_z = max(from_m[2], to_m[2]) + NODE_TOLERANCE_M
        positions = cast(Iterable[tuple[int, Point3]], self.G.nodes(data="position_m"))
        near = [
            n
            for n, p in positions
            if low_x <= p[0] <= high_x
            and low_z <= p[2] <= high_z
            and (n in (u, v) or self.G.degree(n) == 2)
            and _projection_xz(p, from_m, to_m)[1] <= NODE_TOLERANCE_M
        ]
        if u not in near or v not in near:
            return []
        try:
            path = nx.shortest_path(self.G.subgraph(near), u, v, weight="length_m")
        except nx.NetworkXNoPath:
            return []
        return list(itertools.pairwise(path))

    def _cut_off(self, u: int, v: int, interior: Iterable[int]) -> str | None:
        """After the edges between u and v were removed: a tag or point of interest now cut off
        from others it could reach before ("tag 305", from the part holding the fewest), or
        None. Parts without any are dead ends, and may go."""
        if nx.has_path(self.G, u, v):
            return None
        by_node: dict[int, list[str]] = {}
        for t, anchor in self.tags.items():
            by_node.setdefault(anchor.node, []).append(f"tag {t}")
        for poi in self.pois:
            by_node.setdefault(poi.node, []).append(f"point of interest {poi.name!r}")
        parts: list[tuple[set[int], list[str]]] = []
        for node in (u, v, *interior):
            if any(node in part for part, _ in parts):
                continue
            part = nx.node_connected_component(self.G, node)
            parts.append((part, sorted(name for n in part for name in by_node.get(n, ()))))
        held = [names for _, names in parts if names]
        if len(held) < 2:
            return None
        fewest = min(held, key=len)
        more = f" (and {len(fewest) - 1} more)" if len(fewest) > 1 else ""
        return f"{fewest[0]}{more}"

    def _anchors(self, node: int) -> list[str]:
        names = [f"tag {t}" for t, a in self.tags.items() if a.node == node]
        names += [f"point of interest {p.name!r}" for p in self.pois if p.node == node]
        return names

    def _poi(self, name: str, at_m: Point3 | None) -> int:
        """The index of the point of interest named ``name`` (the nearest to ``at_m`` when given,
        within POI_TOLERANCE_M); EditInvalid naming ``name`` or ``at``."""
        if not self.poi_names.get(name, 0):
            raise EditInvalid("name", f"no point of interest named {name!r}")
        found = [k for k, p in enumerate(self.pois) if p.name == name]
        if at_m is None:
            if len({self.pois[k].node for k in found}) > 1:
                raise EditInvalid(
                    "at", f"{len(found)} points of interest are named {name!r}: say which by 'at'"
                )
            return found[0]
        self._floor(at_m, "at")
        k = min(found, key=lambda k: _distance_3d(self.pois[k].position_m, at_m))
        distance_m = _distance_3d(self.pois[k].position_m, at_m)
        if distance_m > POI_TOLERANCE_M:
            raise EditInvalid(
                "at",
                f"no point of interest named {name!r} within {POI_TOLERANCE_M} m of "
                f"{_shown(at_m)} (the nearest is {distance_m:.1f} m away)",
            )
        return k

    def _edge_kind(self, u: int, v: int) -> str:
        data = self.G.edges[u, v]
        return DOOR if data.get("door") else str(data["kind"])

    def _position(self, node: int) -> Point3:
        x, y, z = self.G.nodes[node]["position_m"]
        return (float(x), float(y), float(z))

    def _update_kind(self, node: int) -> None:
        """A node where three or more walk edges meet is a junction; a junction an edit left
        with fewer is a plain node."""
        if node not in self.G:
            return
        walks = sum(
            1 for other in self.G.neighbors(node) if self.G.edges[node, other]["kind"] == WALK
        )
        data = self.G.nodes[node]
        if walks >= 3:
            data["kind"] = JUNCTION
        elif data["kind"] == JUNCTION and walks < 3:
            data["kind"] = NODE


def _given(point: Point3 | None) -> Point3:
    if point is None:  # edit_from_json requires it: only a CorridorEdit made by hand lacks it
        raise EditInvalid("", "the edit lacks a point its op needs")
    return point


def _shown(point_m: Sequence[float]) -> str:
    return "[{:.2f}, {:.2f}, {:.2f}]".format(*point_m)


def _lerp(a: Point3, b: Point3, t: float) -> Point3:
    return (a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1]), a[2] + t * (b[2] - a[2]))


def _distance_3d(a: Sequence[float], b: Sequence[float]) -> float:
    return math.dist((a[0], a[1], a[2]), (b[0], b[1], b[2]))


def _distance_xz(a: Sequence[float], b: Sequence[float]) -> float:
    return math.hypot(a[0] - b[0], a[2] - b[2])


def _projection_xz(
    point: Sequence[float], a: Sequence[float], b: Sequence[float]
) -> tuple[float, float]:
    """(t, horizontal distance) of the nearest point a + t (b − a), t in [0, 1], to ``point``."""
    dx, dz = b[0] - a[0], b[2] - a[2]
    length2 = dx * dx + dz * dz
    t = 0.0 if length2 == 0 else ((point[0] - a[0]) * dx + (point[2] - a[2]) * dz) / length2
    t = min(1.0, max(0.0, t))
    return t, math.hypot(a[0] + t * dx - point[0], a[2] + t * dz - point[2])


def with_edited_pois(result: MapResult, pg: PathGraph) -> MapResult:
    """``result`` with the points of interest of the edited graph ``pg`` (added, renamed and
    removed by edits) in place of its own, for the app's ``waypoints_vertices``: a point of
    interest at the position of one of ``result``'s keeps that one's pose, a new one faces the
    map's axes."""
    kept = [tuple(float(v) for v in T[:3, 3]) for T in result.world_T_poi]
    names: list[str] = []
    poses: list[FloatArray] = []
    for poi in pg.pois:
        pose = np.eye(4)
        pose[:3, 3] = poi.position_m
        for k, position in enumerate(kept):
            if _distance_3d(position, poi.position_m) <= SAME_POSITION_M:
                pose = np.array(result.world_T_poi[k], dtype=np.float64)
                break
        names.append(poi.name)
        poses.append(pose)
    world_T_poi = np.array(poses, dtype=np.float64).reshape(-1, 4, 4)
    return replace(result, poi_names=tuple(names), world_T_poi=world_T_poi)
