"""A long walk's app-map lists the navigation graph and a bounded share of its poses, not every
pose (the app caps a map file at 10 MiB; a 100,000-pose walk listed whole is 27 MiB), and the app
model still finds no crash in it."""

from __future__ import annotations

import json
from itertools import pairwise

import pytest

from app.domain.evaluation.simulate import SimulationConfig, simulate_session
from app.domain.formats.map_io import map_to_app_format
from app.domain.mapping.map_result import MapResult
from app.domain.mapping.slam import optimize_session
from app.domain.navigation.path_graph import PathGraph, build_path_graph
from app.domain.navigation.path_graph.app_format import MAX_APP_POSES, thinned_rows
from app.domain.upload.session import parse_session
from tests.unit.test_app_conformance import assert_app_survives


@pytest.mark.parametrize("n", [0, 1, 2, 3, 10, 11, 499, 500, 501, 4_999, 100_000, 123_457])
@pytest.mark.parametrize("max_rows", [3, 10, 500, MAX_APP_POSES])
def test_thinned_rows_are_bounded_spread_and_keep_both_ends(n: int, max_rows: int) -> None:
    rows = thinned_rows(n, max_rows)
    if n <= max_rows:
        assert rows == list(range(n))
        return
    assert len(rows) <= max_rows
    assert rows[0] == 0
    assert rows[-1] == n - 1
    steps = {b - a for a, b in pairwise(rows[:-1])}
    assert len(steps) <= 1  # evenly spaced (the last row comes on top)
    assert all(a < b for a, b in pairwise(rows))


@pytest.fixture(scope="module")
def long_walk() -> tuple[MapResult, PathGraph]:
    upload = simulate_session(SimulationConfig(num_poses=3000, blocks=(3, 2), seed=2)).upload
    result = optimize_session(parse_session(upload))
    return result, build_path_graph(result)


@pytest.mark.parametrize("with_graph", [True, False], ids=["path graph", "chain"])
def test_a_long_walks_app_map_lists_fewer_vertices_and_the_app_survives(
    long_walk: tuple[MapResult, PathGraph], with_graph: bool
) -> None:
    result, graph = long_walk
    document = map_to_app_format(
        result,
        path_graph=graph if with_graph else None,
        max_poses=300,
    )
    document = json.loads(json.dumps(document, separators=(",", ":"), allow_nan=False))
    vertices = document["odometry_vertices"]
    pose_ids = {int(p) for p in result.pose_id}
    listed_poses = [v for v in vertices if v["poseId"] in pose_ids]
    nodes_that_are_poses = (
        {
            int(result.pose_id[row])
            for _, row in graph.graph.nodes(data="pose_index")
            if row is not None
        }
        if with_graph
        else set()
    )
    assert len(vertices) < len(pose_ids) / 5
    assert len(listed_poses) <= 300 + len(nodes_that_are_poses)
    assert nodes_that_are_poses <= {v["poseId"] for v in vertices}
    assert any("thinned to" in note for note in document["notes"])
    assert_app_survives(document)


def test_a_walk_within_the_limit_lists_every_pose(long_walk: tuple[MapResult, PathGraph]) -> None:
    result = long_walk[0]
    document = map_to_app_format(result, path_graph=None)
    assert len(document["odometry_vertices"]) == len(result.pose_id)
    assert not any("thinned" in note for note in document["notes"])
