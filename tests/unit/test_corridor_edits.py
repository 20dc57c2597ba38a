"""Corridor edits (issue 27) on path graphs made by hand and on corridor skeletons of simulated
walks: each operation, the checks that refuse bad edits, the report of edits that find no anchor,
and the edits found again on a rebuilt graph (other sway, a walk added) whose node ids differ."""

from __future__ import annotations

import itertools
import math
from typing import Any

import networkx as nx
import numpy as np
import pytest

from app.domain.formats.app_model import check_app_map
from app.domain.formats.map_io import map_to_app_format
from app.domain.mapping.slam import optimize_session
from app.domain.navigation.corridor_edits import (
    OPS,
    CorridorEdit,
    EditConflict,
    EditedGraph,
    EditInvalid,
    apply_edits,
    apply_more_edits,
    apply_new_edit,
    apply_new_edit_to,
    edit_from_json,
    quiet_nodes,
)
from app.domain.navigation.instructions import plan_guided_route
from app.domain.navigation.path_graph import (
    JUNCTION,
    NODE,
    STAIRS,
    WALK,
    Anchor,
    PathGraph,
    path_graph_from_json,
    path_graph_to_json,
)
from app.domain.navigation.routing import NodeEnd, PoiEnd, TagEnd, Unreachable, plan_walk
from app.domain.navigation.skeleton import build_skeleton, build_skeleton_from_arrays
from app.domain.upload.session import load_session


def _node(G: nx.Graph, n: int, x: float, y: float, z: float, floor: int, kind: str = NODE) -> None:
    G.add_node(n, position_m=(x, y, z), floor=floor, kind=kind, pose_index=None)


def _edge(G: nx.Graph, u: int, v: int, kind: str = WALK, floor: int = 0) -> None:
    length_m = math.dist(G.nodes[u]["position_m"], G.nodes[v]["position_m"])
    G.add_edge(u, v, length_m=length_m, kind=kind, floor=floor)


def t_building() -> PathGraph:
    """Floor 1 (y 0): a corridor 0–1–3 along x with a branch 1–2 (a left turn at junction 1);
    floor 2 (y 4): 10–11, stairs 0–10. Tags 1, 2, 3 on floor 1, tag 4 on floor 2; 'Kitchen' at
    node 3."""
    G: nx.Graph = nx.Graph()
    _node(G, 0, 0, 0, 0, 0)
    _node(G, 1, 20, 0, 0, 0, JUNCTION)
    _node(G, 2, 20, 0, -20, 0)
    _node(G, 3, 40, 0, 0, 0)
    _node(G, 10, 0, 4, 0, 1)
    _node(G, 11, 20, 4, 0, 1)
    _edge(G, 0, 1)
    _edge(G, 1, 2)
    _edge(G, 1, 3)
    _edge(G, 0, 10, STAIRS)
    _edge(G, 10, 11, WALK, 1)

    def tag(name: str, node: int, p: tuple[float, float, float], floor: int) -> Anchor:
        return Anchor(name=name, node=node, position_m=p, floor=floor)

    return PathGraph(
        graph=G,
        floor_levels_m=(0.0, 4.0),
        tags={
            1: tag("tag 1", 0, (0, 1, 1), 0),
            2: tag("tag 2", 2, (21, 1, -20), 0),
            3: tag("tag 3", 3, (40, 1, 1), 0),
            4: tag("tag 4", 11, (20, 5, 1), 1),
        },
        pois=(tag("Kitchen", 3, (41, 1, 0), 0),),
    )


def edit(document: dict[str, Any]) -> CorridorEdit:
    return edit_from_json(document)


def instructions(pg: PathGraph, start: Any, goal: Any) -> list[str]:
    return [step.instruction for step in plan_guided_route(pg, start, goal).steps]


# --------------------------------------------------------------------------- reading edits


@pytest.mark.parametrize(
    "document",
    [
        {"op": "quiet", "at": [1, 0, 2]},
        {"op": "add_edge", "from": [1, 0, 2], "to": [3, 0, 4], "kind": "door"},
        {"op": "remove_edge", "from": [1, 0, 2], "to": [3, 0, 4]},
        {"op": "move_node", "from": [1, 0, 2], "to": [3, 0, 4.5]},
        {"op": "add_poi", "name": "Lab", "at": [1, 0, 2]},
        {"op": "rename_poi", "name": "Lab", "new_name": "Lab 2"},
        {"op": "rename_poi", "name": "Lab", "new_name": "Lab 2", "at": [1, 0, 2]},
        {"op": "remove_poi", "name": "Lab"},
    ],
)
def test_an_edit_reads_back_as_written(document):
    parsed = edit_from_json(document)
    assert parsed.op in OPS
    assert parsed.to_json() == {
        k: ([float(x) for x in v] if isinstance(v, list) else v) for k, v in document.items()
    }


@pytest.mark.parametrize(
    ("document", "field", "words"),
    [
        ({"op": "straighten", "at": [0, 0, 0]}, "op", "unknown op 'straighten'"),
        ({"at": [0, 0, 0]}, "op", "unknown op None"),
        ({"op": "quiet"}, "at", "quiet needs 'at'"),
        ({"op": "quiet", "at": [0, 0]}, "at", "three numbers"),
        ({"op": "quiet", "at": [0, True, 0]}, "at", "three numbers"),
        ({"op": "quiet", "at": [0, float("nan"), 0]}, "at", "finite"),
        ({"op": "quiet", "at": [0, 10**400, 0]}, "at", "finite"),
        ({"op": "quiet", "at": [0, 0, 0], "form": 1}, "form", "takes no field 'form'"),
        ({"op": "add_edge", "from": [0, 0, 0], "to": [1, 0, 0], "kind": "ramp"}, "kind", "ramp"),
        ({"op": "add_edge", "from": [0, 0, 0], "to": [1, 0, 0]}, "kind", "needs 'kind'"),
        ({"op": "add_poi", "name": "  ", "at": [0, 0, 0]}, "name", "non-empty"),
        ({"op": "add_poi", "name": "x" * 201, "at": [0, 0, 0]}, "name", "at most 200"),
    ],
)
def test_a_malformed_edit_is_refused_naming_the_field(document, field, words):
    with pytest.raises(EditInvalid) as refused:
        edit_from_json(document)
    assert refused.value.field == field
    assert words in str(refused.value)


def test_a_non_object_is_refused():
    with pytest.raises(EditInvalid, match="JSON object"):
        edit_from_json([1, 2])


# --------------------------------------------------------------------------- the operations


def test_quiet_silences_the_turn_announced_at_that_node_only():
    pg = t_building()
    before = instructions(pg, TagEnd(1), TagEnd(2))
    assert "turn left" in before
    quiet = apply_new_edit(pg, edit({"op": "quiet", "at": [20.4, 0.1, 0.5]}))
    assert quiet_nodes(quiet) == {1}
    after = instructions(quiet, TagEnd(1), TagEnd(2))
    assert not any("turn" in words for words in after), after
    assert after[-1] == before[-1]  # the arrival is the same
    assert quiet_nodes(pg) == frozenset()  # the graph edited is a copy
    with pytest.raises(EditConflict, match="quiet already"):
        apply_new_edit(quiet, edit({"op": "quiet", "at": [20, 0, 0]}))


def test_add_edge_makes_a_shortcut_and_a_door_is_walked_through():
    pg = t_building()
    before = plan_walk(pg, TagEnd(2), TagEnd(3)).length_m
    door = apply_new_edit(
        pg, edit({"op": "add_edge", "from": [20, 0, -20], "to": [40, 0, 0], "kind": "door"})
    )
    data = door.graph.edges[2, 3]
    assert data["kind"] == WALK
    assert data["door"] is True
    assert data["length_m"] == pytest.approx(math.hypot(20, 20))
    assert plan_walk(door, TagEnd(2), TagEnd(3)).length_m == pytest.approx(math.hypot(20, 20))
    assert before == pytest.approx(40.0)


def test_add_edge_to_a_corridor_splits_it_and_makes_a_junction():
    pg = t_building()
    edited = apply_new_edit(
        pg, edit({"op": "add_edge", "from": [10, 0, 0.8], "to": [20, 0, -20], "kind": "walk"})
    )
    new = max(edited.graph.nodes)
    assert new == 12  # above the largest id
    assert edited.graph.nodes[new]["position_m"] == pytest.approx((10.0, 0.0, 0.0))
    assert edited.graph.nodes[new]["kind"] == JUNCTION
    assert not edited.graph.has_edge(0, 1)
    assert edited.graph.has_edge(0, new)
    assert edited.graph.has_edge(new, 1)
    total_m = edited.graph.edges[0, new]["length_m"] + edited.graph.edges[new, 1]["length_m"]
    assert total_m == pytest.approx(20.0)


def test_stairs_join_two_floors():
    pg = t_building()
    edited = apply_new_edit(
        pg, edit({"op": "add_edge", "from": [40, 0, 0], "to": [20, 4, 0], "kind": "stairs"})
    )
    assert edited.graph.edges[3, 11]["kind"] == STAIRS
    assert edited.graph.edges[3, 11]["floor"] == 0
    route = plan_walk(edited, TagEnd(3), TagEnd(4))
    assert route.length_m < plan_walk(pg, TagEnd(3), TagEnd(4)).length_m
    with pytest.raises(Unreachable):
        plan_walk(pg, TagEnd(3), TagEnd(4), avoid=frozenset({"stairs"}))


@pytest.mark.parametrize(
    ("document", "error", "field", "words"),
    [
        (
            {"op": "add_edge", "from": [0, 0, 0], "to": [20, 4, 0], "kind": "walk"},
            EditInvalid,
            "to",
            "use stairs or elevator",
        ),
        (
            {"op": "add_edge", "from": [0, 0, 0], "to": [20, 0, 0], "kind": "elevator"},
            EditInvalid,
            "to",
            "join two floors",
        ),
        (
            {"op": "add_edge", "from": [0, 0, 0], "to": [0.5, 0, 0.5], "kind": "walk"},
            EditInvalid,
            "to",
            "same node",
        ),
        (
            {"op": "add_edge", "from": [0, 0, 0], "to": [20, 0, 0], "kind": "walk"},
            EditConflict,
            "to",
            "exists already",
        ),
        (
            {"op": "add_edge", "from": [0, 0, 0], "to": [30, 0, -30], "kind": "walk"},
            EditInvalid,
            "to",
            "no node or corridor within",
        ),
        ({"op": "quiet", "at": [500, 0, 0]}, EditInvalid, "at", "outside the map"),
        ({"op": "quiet", "at": [0, 9, 0]}, EditInvalid, "at", "on no floor"),
        ({"op": "quiet", "at": [10, 0, 0]}, EditInvalid, "at", "no node within 1.5 m"),
        (
            {"op": "remove_edge", "from": [0, 0, 0], "to": [40, 0, 0]},
            EditInvalid,
            "to",
            "no edge joins",
        ),
        (
            {"op": "remove_edge", "from": [20, 0, 0], "to": [20, 0, 0.5]},
            EditInvalid,
            "to",
            "same node",
        ),
        (
            {"op": "remove_edge", "from": [20, 0, 0], "to": [40, 0, 0]},
            EditConflict,
            "to",
            "would cut point of interest 'Kitchen' (and 1 more) off",
        ),
        (
            {"op": "remove_edge", "from": [0, 0, 0], "to": [0, 4, 0]},
            EditConflict,
            "to",
            "would cut tag 4 off",
        ),
        (
            {"op": "move_node", "from": [20, 0, -20], "to": [20, 4, -20]},
            EditInvalid,
            "to",
            "within its floor",
        ),
        (
            {"op": "add_poi", "name": "Kitchen", "at": [30, 0, 1]},
            EditConflict,
            "name",
            "exists already",
        ),
        (
            {"op": "rename_poi", "name": "Lab", "new_name": "Lab 2"},
            EditInvalid,
            "name",
            "no point of interest named 'Lab'",
        ),
        (
            {"op": "rename_poi", "name": "Kitchen", "new_name": "Den", "at": [0, 0, 0]},
            EditInvalid,
            "at",
            "within 5.0 m",
        ),
        ({"op": "remove_poi", "name": "kitchen"}, EditInvalid, "name", "no point of interest"),
    ],
)
def test_a_bad_edit_is_refused_naming_what_is_wrong(document, error, field, words):
    pg = t_building()
    before = path_graph_to_json(pg)
    with pytest.raises(error) as refused:
        apply_new_edit(pg, edit(document))
    assert refused.value.field == field
    assert words in str(refused.value), str(refused.value)
    assert path_graph_to_json(pg) == before  # the graph given is never changed


def test_a_corridor_parallel_to_a_split_one_is_a_duplicate():
    """An edge whose corridor was split (by a point of interest, say) is still there: adding it
    again is a duplicate, and removing it removes the run."""
    pg = apply_new_edit(t_building(), edit({"op": "add_poi", "name": "Lab", "at": [10, 0, 3]}))
    assert not pg.graph.has_edge(0, 1)
    with pytest.raises(EditConflict, match="exists already"):
        apply_new_edit(
            pg, edit({"op": "add_edge", "from": [0, 0, 0], "to": [20, 0, 0], "kind": "walk"})
        )
    with pytest.raises(EditConflict, match="would cut"):
        apply_new_edit(pg, edit({"op": "remove_edge", "from": [0, 0, 0], "to": [20, 0, 0]}))


def test_remove_edge_after_a_shortcut_keeps_everything_reachable():
    pg = t_building()
    pg = apply_new_edit(
        pg, edit({"op": "add_edge", "from": [20, 0, -20], "to": [40, 0, 0], "kind": "walk"})
    )
    pg = apply_new_edit(pg, edit({"op": "remove_edge", "from": [20, 0, 0], "to": [40, 0, 0]}))
    assert not pg.graph.has_edge(1, 3)
    assert plan_walk(pg, TagEnd(1), PoiEnd("Kitchen")).length_m == pytest.approx(
        40 + math.hypot(20, 20)
    )
    assert pg.graph.nodes[1]["kind"] == NODE  # two corridors meet there now


def test_move_node_straightens_a_corridor():
    pg = t_building()
    moved = apply_new_edit(
        pg, edit({"op": "move_node", "from": [20, 0, -20], "to": [25, 0.3, -20]})
    )
    assert moved.graph.nodes[2]["position_m"] == (25.0, 0.0, -20.0)  # keeps its height
    assert moved.graph.edges[1, 2]["length_m"] == pytest.approx(math.hypot(5, 20))
    assert pg.graph.nodes[2]["position_m"] == (20, 0, -20)


def test_points_of_interest_are_added_renamed_and_removed():
    pg = apply_new_edit(t_building(), edit({"op": "add_poi", "name": "Lab", "at": [10, 0, 3]}))
    lab = next(p for p in pg.pois if p.name == "Lab")
    assert lab.position_m == (10.0, 0.0, 3.0)
    assert pg.graph.nodes[lab.node]["position_m"] == pytest.approx((10.0, 0.0, 0.0))
    assert instructions(pg, TagEnd(1), PoiEnd("Lab"))[-1] == "arrive at Lab, on your right"
    pg = apply_new_edit(
        pg, edit({"op": "rename_poi", "name": "Lab", "new_name": "Lab 2", "at": [10, 0, 2]})
    )
    assert sorted(p.name for p in pg.pois) == ["Kitchen", "Lab 2"]
    with pytest.raises(EditConflict, match="'Kitchen' exists already"):
        apply_new_edit(pg, edit({"op": "rename_poi", "name": "Lab 2", "new_name": "Kitchen"}))
    pg = apply_new_edit(pg, edit({"op": "remove_poi", "name": "Kitchen"}))
    assert [p.name for p in pg.pois] == ["Lab 2"]
    round_trip = path_graph_from_json(path_graph_to_json(pg))
    assert [p.name for p in round_trip.pois] == ["Lab 2"]


def test_a_poi_near_a_node_is_reached_from_it():
    pg = apply_new_edit(t_building(), edit({"op": "add_poi", "name": "Desk", "at": [39, 0, 3]}))
    assert next(p for p in pg.pois if p.name == "Desk").node == 3
    assert pg.graph.number_of_nodes() == 6


# --------------------------------------------------------------------------- applying a list


def test_edits_that_find_no_anchor_are_reported_and_the_rest_applied():
    pg = t_building()
    edits = [
        edit({"op": "quiet", "at": [20, 0, 0]}),
        edit({"op": "quiet", "at": [30, 0, 0]}),  # no node there
        edit({"op": "remove_edge", "from": [20, 0, 0], "to": [40, 0, 0]}),  # would cut Kitchen
        edit({"op": "add_edge", "from": [20, 0, -20], "to": [40, 0, 0], "kind": "walk"}),
        edit({"op": "remove_edge", "from": [20, 0, 0], "to": [40, 0, 0]}),  # now it may go
        edit({"op": "rename_poi", "name": "Lobby", "new_name": "Hall"}),
    ]
    edited = apply_edits(pg, edits)
    assert [o.applied for o in edited.outcomes] == [True, False, False, True, True, False]
    assert edited.applied_count == 3
    assert edited.outcomes[1].field == "at"
    assert "no node within 1.5 m of [30.00, 0.00, 0.00] on floor 1" in (
        edited.outcomes[1].reason or ""
    )
    assert "would cut" in (edited.outcomes[2].reason or "")
    assert "no point of interest named 'Lobby'" in (edited.outcomes[5].reason or "")
    assert quiet_nodes(edited.path_graph) == {1}
    assert not edited.path_graph.graph.has_edge(1, 3)
    assert nx.is_connected(edited.path_graph.graph)


def test_a_failed_add_edge_leaves_no_split_behind():
    """Both ends on one corridor, 1 m apart: the first end splits it, the second finds that node:
    a self-loop, refused, and the split undone."""
    pg = t_building()
    document = {"op": "add_edge", "from": [8, 0, 0.3], "to": [8.8, 0, 0.3], "kind": "walk"}
    edited = apply_edits(pg, [edit(document)])
    assert not edited.outcomes[0].applied
    assert sorted(edited.path_graph.graph.nodes) == sorted(pg.graph.nodes)
    assert edited.path_graph.graph.has_edge(0, 1)


def test_no_edits_is_the_graph_itself():
    pg = t_building()
    assert apply_edits(pg, []).path_graph is pg


def test_an_empty_graph_takes_no_edit():
    edited = apply_edits(PathGraph(), [edit({"op": "quiet", "at": [0, 0, 0]})])
    assert edited.outcomes[0].applied is False
    assert "empty" in (edited.outcomes[0].reason or "")


# --------------------------------------------------------------------------- a rebuilt graph


def walk(corners: list[tuple[float, float, float]], seed: int, sway_m: float = 0.15) -> np.ndarray:
    """A walk through ``corners`` (x, 0, z) at 0.4 m steps, swaying ``sway_m``, phone at 1.2 m."""
    rng = np.random.default_rng(seed)
    points = []
    for a, b in itertools.pairwise(corners):
        start, end = np.array(a, float), np.array(b, float)
        n = max(2, int(np.linalg.norm(end - start) / 0.4))
        points += [start + t * (end - start) for t in np.linspace(0, 1, n, endpoint=False)]
    points.append(np.array(corners[-1], float))
    xyz = np.array(points)
    xyz[:, [0, 2]] += rng.normal(0, sway_m, (len(xyz), 2))
    xyz[:, 1] = 1.2 + rng.normal(0, 0.02, len(xyz))
    return xyz


T_WALK = [(0.0, 0.0, 0.0), (40.0, 0.0, 0.0), (20.0, 0.0, 0.0), (20.0, 0.0, -20.0)]
MORE_WALK = [(20.0, 0.0, -20.0), (20.0, 0.0, -30.0), (40.0, 0.0, -30.0)]
TAGS = {"tag_ids": [1, 2, 3], "tag_positions_m": [(0, 1.5, 1), (40, 1.5, 1), (21, 1.5, -20)]}


def skeleton(*walks: np.ndarray) -> PathGraph:
    return build_skeleton_from_arrays(np.vstack(walks), **TAGS)


def node_near(pg: PathGraph, x: float, z: float) -> list[float]:
    """The position of the node of ``pg`` nearest (x, z): where an operator clicks."""
    nearest = min(
        pg.graph.nodes,
        key=lambda n: math.hypot(
            pg.graph.nodes[n]["position_m"][0] - x, pg.graph.nodes[n]["position_m"][2] - z
        ),
    )
    return [float(v) for v in pg.graph.nodes[nearest]["position_m"]]


def test_edits_are_found_again_after_a_rebuild_and_after_a_walk_is_added():
    """Edits made on the skeleton of one walk (clicking its nodes) apply to the skeleton of
    another walk of the same corridors, and to the skeleton with a further walk added, though
    their nodes moved and were numbered anew."""
    first = skeleton(walk(T_WALK, seed=1))
    level = first.floor_levels_m[0]
    junction, branch_end, east_end = (
        node_near(first, 20, 0),
        node_near(first, 20, -20),
        node_near(first, 40, 0),
    )
    documents = [
        {"op": "quiet", "at": junction},
        {"op": "move_node", "from": branch_end, "to": [branch_end[0] + 1.0, level, branch_end[2]]},
        {
            "op": "add_edge",
            "from": [branch_end[0] + 1.0, level, branch_end[2]],
            "to": east_end,
            "kind": "walk",
        },
        {"op": "add_poi", "name": "Lab", "at": [10.0, level, 2.0]},
    ]
    edits = []
    pg = first
    for document in documents:
        pg = apply_new_edit(pg, edit(document))  # each one applies when it is made
        edits.append(edit(document))
    rebuilt = skeleton(walk(T_WALK, seed=7))
    grown = skeleton(walk(T_WALK, seed=1), walk(MORE_WALK, seed=2))
    for other in (rebuilt, grown):
        assert set(other.graph.nodes) != set(first.graph.nodes) or any(
            other.graph.nodes[n]["position_m"] != first.graph.nodes[n]["position_m"]
            for n in other.graph.nodes
            if n in first.graph
        )
        edited = apply_edits(other, edits)
        assert all(o.applied for o in edited.outcomes), edited.outcomes
        assert len(quiet_nodes(edited.path_graph)) == 1
        assert [p.name for p in edited.path_graph.pois] == ["Lab"]
        assert plan_walk(edited.path_graph, TagEnd(2), PoiEnd("Lab")).length_m > 0
        assert nx.is_connected(edited.path_graph.graph)


def test_an_edit_whose_place_is_gone_is_reported_not_dropped():
    """A quiet on the corridor the grown map has and the first map lacks: applied there,
    reported on the first."""
    grown = skeleton(walk(T_WALK, seed=1), walk(MORE_WALK, seed=2))
    corner = node_near(grown, 20, -30)
    quiet = edit({"op": "quiet", "at": corner})
    assert apply_edits(grown, [quiet]).outcomes[0].applied
    outcome = apply_edits(skeleton(walk(T_WALK, seed=1)), [quiet]).outcomes[0]
    assert not outcome.applied
    assert outcome.field == "at"
    assert "no node within 1.5 m" in (outcome.reason or "")


def test_a_node_route_still_works_on_an_edited_graph():
    pg = apply_new_edit(
        t_building(),
        edit({"op": "add_edge", "from": [10, 0, 0], "to": [20, 0, -20], "kind": "walk"}),
    )
    assert plan_walk(pg, NodeEnd(12), TagEnd(2)).length_m == pytest.approx(math.hypot(10, 20))


# --------------------------------------------------------------------------- the app's model


def test_the_apps_map_of_an_edited_real_map_conforms(data_dir):
    """Every kind of edit an operator makes, on the skeleton of a real walk (floor_2_straight):
    the app-map made from the edited graph passes the app model's check (one connected graph,
    links at both ends, every tag routable from every vertex)."""
    result = optimize_session(load_session(data_dir / "sessions" / "floor_2_straight.json"))
    pg = build_skeleton(result)
    G = pg.graph
    ends = [n for n in G.nodes if G.degree(n) == 1]
    bends = [n for n in G.nodes if G.degree(n) == 2]
    assert len(ends) >= 2
    assert len(bends) >= 2

    def at(n: int) -> list[float]:
        return [float(v) for v in G.nodes[n]["position_m"]]

    moved = bends[len(bends) // 2]
    documents = [
        {"op": "quiet", "at": at(bends[0])},
        {
            "op": "move_node",
            "from": at(moved),
            "to": [at(moved)[0] + 0.4, at(moved)[1], at(moved)[2]],
        },
        {"op": "add_edge", "from": at(ends[0]), "to": at(ends[-1]), "kind": "door"},
        {"op": "add_poi", "name": "Printer", "at": at(bends[-1])},
        {"op": "rename_poi", "name": "Printer", "new_name": "Printer 2"},
    ]
    edited = pg
    for document in documents:
        edited = apply_new_edit(edited, edit(document))
    assert len(quiet_nodes(edited)) == 1
    assert [p.name for p in edited.pois] == ["Printer 2"]
    report = check_app_map(map_to_app_format(result, path_graph=edited))
    assert report.ok, str(report)
    assert report.components == 1
    assert report.pairs > 0
    # and after removing the door again
    removed = apply_new_edit(
        edited, edit({"op": "remove_edge", "from": at(ends[0]), "to": at(ends[-1])})
    )
    assert check_app_map(map_to_app_format(result, path_graph=removed)).ok


# --------------------------------------------------------------------------- one at a time


def a_line_with_a_middle_node() -> PathGraph:
    """Floor 1: 0 (x 0) – 5 (x 10) – 1 (x 20) – 2 (x 20, z −20); node 5, the largest id, is a
    plain node in the middle of a corridor. Tags 1 at node 0 and 2 at node 2."""
    G: nx.Graph = nx.Graph()
    _node(G, 0, 0, 0, 0, 0)
    _node(G, 5, 10, 0, 0, 0)
    _node(G, 1, 20, 0, 0, 0)
    _node(G, 2, 20, 0, -20, 0)
    _edge(G, 0, 5)
    _edge(G, 5, 1)
    _edge(G, 1, 2)
    anchor = Anchor
    return PathGraph(
        graph=G,
        floor_levels_m=(0.0,),
        tags={
            1: anchor(name="tag 1", node=0, position_m=(0, 1, 0), floor=0),
            2: anchor(name="tag 2", node=2, position_m=(20, 1, -20), floor=0),
        },
        pois=(),
    )


#: Edits whose node ids depend on the order of what came before: a shortcut, the corridor
#: 0–5–1 removed (node 5, the largest id, goes with it), a point of interest splitting an edge
#: (a new node: its id is not max + 1 any more), one that does not apply, a move far out (the
#: map's extent is the unedited graph's: a point near the moved node but 20 m past the
#: unedited map is refused), renames and a quiet.
ONE_AT_A_TIME = [
    {"op": "add_edge", "from": [0, 0, 0], "to": [20, 0, -20], "kind": "walk"},
    {"op": "remove_edge", "from": [0, 0, 0], "to": [20, 0, 0]},
    {"op": "add_poi", "name": "Desk", "at": [10, 0, -13]},
    {"op": "quiet", "at": [10, 0, 0]},  # node 5 is gone: not applied
    {"op": "move_node", "from": [20, 0, 0], "to": [38, 0, 0]},
    {"op": "add_poi", "name": "Far", "at": [55, 0, 0]},  # 35 m past x 20: not applied
    {"op": "rename_poi", "name": "Desk", "new_name": "Desk 2"},
    {"op": "add_poi", "name": "Desk", "at": [20, 0, -10]},
    {"op": "quiet", "at": [20, 0, -20]},
    {"op": "remove_poi", "name": "Desk"},
]


def same_graph(a: PathGraph, b: PathGraph) -> None:
    assert list(a.graph.nodes(data=True)) == list(b.graph.nodes(data=True))
    assert sorted(
        (min(u, v), max(u, v), sorted(d.items())) for u, v, d in a.graph.edges(data=True)
    ) == sorted((min(u, v), max(u, v), sorted(d.items())) for u, v, d in b.graph.edges(data=True))
    assert a.pois == b.pois
    assert a.tags == b.tags
    assert quiet_nodes(a) == quiet_nodes(b)


def test_edits_applied_one_at_a_time_make_what_all_at_once_make():
    """What a POST does (the new edit applied to the kept edited graph) is what re-applying
    every edit does (another process, a restart): the same node ids, the same outcomes."""
    pg = a_line_with_a_middle_node()
    edits = [edit(document) for document in ONE_AT_A_TIME]
    whole = apply_edits(pg, edits)
    assert [o.applied for o in whole.outcomes] == [
        True, True, True, False, True, False, True, True, True, True
    ]  # fmt: skip
    assert 5 not in whole.path_graph.graph
    assert max(whole.path_graph.graph) == 7  # ids 6 and 7: the two edges split
    one_by_one = EditedGraph(path_graph=pg, outcomes=())
    strict = EditedGraph(path_graph=pg, outcomes=())
    for k, one in enumerate(edits):
        one_by_one = apply_more_edits(one_by_one, [one])
        if whole.outcomes[k].applied:
            strict = apply_new_edit_to(strict, one)
        else:
            with pytest.raises(EditInvalid) as refused:
                apply_new_edit_to(strict, one)
            assert refused.value.reason == whole.outcomes[k].reason
            strict = apply_more_edits(strict, [one])
    for made in (one_by_one, strict):
        same_graph(made.path_graph, whole.path_graph)
        assert made.outcomes == whole.outcomes
    halves = apply_more_edits(apply_edits(pg, edits[:4]), edits[4:])
    same_graph(halves.path_graph, whole.path_graph)
    assert pg.graph.number_of_nodes() == 4  # never changed
    assert [p.name for p in whole.path_graph.pois] == ["Desk 2"]


def test_a_new_edit_is_checked_against_the_unedited_maps_extent():
    """A point past the map by more than the margin is refused also after an edit moved a node
    out there: else it would be stored, and reported not applied at the next re-application."""
    pg = a_line_with_a_middle_node()
    moved = apply_new_edit_to(
        EditedGraph(path_graph=pg, outcomes=()),
        edit({"op": "move_node", "from": [20, 0, -20], "to": [38, 0, -20]}),
    )
    far = edit({"op": "add_poi", "name": "Far", "at": [55, 0, -20]})
    with pytest.raises(EditInvalid, match="outside the map"):
        apply_new_edit_to(moved, far)
    assert (
        not apply_edits(
            pg, [edit({"op": "move_node", "from": [20, 0, -20], "to": [38, 0, -20]}), far]
        )
        .outcomes[1]
        .applied
    )


def test_many_points_of_interest_each_name_once():
    """Names of points of interest stay unique through adds, renames and removals (kept as a
    count per name, not a search of them all)."""
    pg = a_line_with_a_middle_node()
    documents: list[dict[str, Any]] = [
        {"op": "add_poi", "name": f"Room {k}", "at": [float(k % 20), 0, 0]} for k in range(300)
    ]
    documents += [
        {"op": "add_poi", "name": "Room 7", "at": [1, 0, 0]},  # taken
        {"op": "rename_poi", "name": "Room 8", "new_name": "Room 9"},  # taken
        {"op": "remove_poi", "name": "Room 9"},
        {"op": "rename_poi", "name": "Room 8", "new_name": "Room 9"},  # free now
        {"op": "add_poi", "name": "Room 8", "at": [1, 0, 0]},  # free now
        {"op": "remove_poi", "name": "Room 400"},  # none
    ]
    outcomes = apply_edits(pg, [edit(d) for d in documents]).outcomes
    assert all(o.applied for o in outcomes[:300])
    assert [o.applied for o in outcomes[300:]] == [False, False, True, True, True, False]
    assert outcomes[300].field == "name"
    assert outcomes[301].field == "new_name"
    assert outcomes[305].field == "name"
