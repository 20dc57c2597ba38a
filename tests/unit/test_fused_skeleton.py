"""One corridor skeleton fused from all the walks of a building map (issue 26):
``build_skeleton(result, walk_starts=…)`` / ``build_skeleton_from_arrays(…, walk_starts=…)``."""

from __future__ import annotations

import itertools
from functools import cache

import networkx as nx
import numpy as np
import pytest

from app.domain.errors import ParameterError
from app.domain.evaluation.simulate import SimulationConfig
from app.domain.evaluation.simulate_building import simulate_building_sessions
from app.domain.formats.app_model import check_app_map
from app.domain.formats.map_io import map_to_app_format
from app.domain.mapping.joint import JointMap, optimize_sessions
from app.domain.navigation.instructions import plan_guided_route
from app.domain.navigation.path_graph import JUNCTION, WALK, PathGraph
from app.domain.navigation.routing import TagEnd
from app.domain.navigation.skeleton import build_skeleton, build_skeleton_from_arrays
from app.domain.upload.session import parse_session
from tests.unit.walks import walk


@cache
def joint_map() -> JointMap:
    sim = simulate_building_sessions(SimulationConfig(num_poses=800, seed=5), count=3)
    return optimize_sessions([parse_session(s.upload) for s in sim.sessions])


def starts(joint: JointMap) -> list[int]:
    return [part.pose_rows.start for part in joint.parts]


def walk_length_m(pg: PathGraph) -> float:
    return sum(d["length_m"] for _, _, d in pg.graph.edges(data=True) if d["kind"] == WALK)


def junction_count(pg: PathGraph) -> int:
    return sum(1 for _, d in pg.graph.nodes(data=True) if d["kind"] == JUNCTION)


def test_no_corridor_joins_the_end_of_one_walk_to_the_start_of_the_next() -> None:
    # Two walks of two corridors 12 m apart: as one walk they would be joined by a diagonal.
    first = walk((0, 0), (20, 0))
    second = walk((0, 12), (20, 12))
    positions = np.concatenate([first, second])
    fused = build_skeleton_from_arrays(positions, walk_starts=[0, len(first)])
    assert nx.number_connected_components(fused.graph) == 2
    assert 38.0 <= walk_length_m(fused) <= 41.0
    as_one_walk = build_skeleton_from_arrays(positions)
    assert nx.number_connected_components(as_one_walk.graph) == 1
    assert walk_length_m(as_one_walk) > 50.0  # … with the 20 m diagonal from (20, 0) to (0, 12)


def test_walks_of_one_corridor_are_one_centreline_not_more_branches() -> None:
    # Five walks of one L corridor, each with its own offset from the centre: one L, no junction.
    offsets_m = (-0.5, 0.4, -0.2, 0.6, 0.0)
    walks = [walk((0, d), (25 + d, d), (25 + d, 20)) for d in offsets_m]
    positions = np.concatenate(walks)
    walk_starts = np.cumsum([0, *(len(w) for w in walks[:-1])])
    fused = build_skeleton_from_arrays(positions, walk_starts=walk_starts.tolist())
    assert nx.is_connected(fused.graph)
    assert junction_count(fused) == 0
    assert not nx.cycle_basis(fused.graph)
    assert 40.0 <= walk_length_m(fused) <= 46.0
    single = build_skeleton_from_arrays(walks[0])
    assert walk_length_m(fused) <= walk_length_m(single) + 2.0


def test_a_building_map_is_one_fused_skeleton_with_every_tag() -> None:
    joint = joint_map()
    pg = build_skeleton(joint.map, walk_starts=starts(joint))
    assert nx.is_connected(pg.graph)
    assert set(pg.tags) == {int(t) for t in joint.map.tag_ids}
    # the walks' own skeletons together are longer than the fused one: shared corridors count once
    own = 0.0
    for part in joint.parts:
        own += walk_length_m(
            build_skeleton_from_arrays(joint.map.world_T_phone[part.pose_rows, :3, 3])
        )
    assert walk_length_m(pg) < own


def test_the_apps_map_of_a_building_map_conforms() -> None:
    joint = joint_map()
    pg = build_skeleton(joint.map, walk_starts=starts(joint))
    report = check_app_map(map_to_app_format(joint.map, path_graph=pg))
    assert report.ok, str(report)
    assert report.components == 1
    assert report.pairs > 0


@pytest.mark.parametrize("walk_starts", [[-1], [0, 10_000]])
def test_walk_starts_outside_the_walk_are_refused(walk_starts) -> None:
    with pytest.raises(ParameterError, match="walk_starts"):
        build_skeleton_from_arrays(walk((0, 0), (5, 0)), walk_starts=walk_starts)


def test_a_walk_added_elsewhere_changes_nothing_where_it_did_not_go() -> None:
    # The first walks: a T of corridors with tags; the walk added: corridors beyond its west end,
    # reaching farther west and south than the first walks (so the raster's extent grows).
    first = [
        walk((0, 0), (30, 0), (30, 25)),
        walk((15, 0.4), (15, -20)),
    ]
    added = walk((-0.3, 0.2), (-25.1, 0.2), (-25.1, -23.1))
    tag_ids = [1, 2, 3, 4, 5, 6]
    tags = [(2, 1.4, 1.4), (14, 1.4, -1.4), (16.4, 1.4, -15), (28.6, 1.4, 12), (31.4, 1.4, 40)]
    tags.append((-20, 1.4, 1.4))

    def fused(walks):
        starts = np.cumsum([0, *(len(w) for w in walks[:-1])]).tolist()
        return build_skeleton_from_arrays(
            np.concatenate(walks), walk_starts=starts, tag_ids=tag_ids, tag_positions_m=tags
        )

    before, after = fused(first), fused([*first, added])

    def far_edges(pg):  # walk edges more than 6 m from the added walk: (E, 2, 3) ends, m
        G, out = pg.graph, []
        for u, v in G.edges:
            ends = np.array([G.nodes[u]["position_m"], G.nodes[v]["position_m"]])
            if min(np.hypot(*(added[:, [0, 2]] - p[[0, 2]]).T).min() for p in ends) > 6.0:
                out.append(ends[np.lexsort(ends.T[::-1])])
        return np.array(sorted(out, key=lambda e: tuple(e.ravel())))

    # the same edges, to a few cm (a corridor's line now ends farther away: it may tilt by 1 cm)
    np.testing.assert_allclose(far_edges(before), far_edges(after), atol=0.05)
    for a, b in itertools.permutations([2, 3, 4, 5], 2):  # routes the added walk did not visit
        told = [
            [s.instruction for s in plan_guided_route(pg, TagEnd(a), TagEnd(b)).steps]
            for pg in (before, after)
        ]
        assert told[0] == told[1]
    assert walk_length_m(after) > walk_length_m(before) + 40.0  # … and the new corridors are there
    plan_guided_route(after, TagEnd(1), TagEnd(6))  # reachable through the fused skeleton
