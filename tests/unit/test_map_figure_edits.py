"""The map page's figure drawn from the edited path graph (issue 39): a point of interest added by
a corridor edit is in the figure's points of interest, and an added edge in its path graph."""

from __future__ import annotations

import numpy as np

from app.domain.formats.map_figure import with_path_graph
from app.domain.navigation.corridor_edits import apply_edits, edit_from_json
from app.domain.navigation.path_graph import build_path_graph_from_arrays


def make_corridor(n: int = 21, length_m: float = 20.0):  # type: ignore[no-untyped-def]
    """A straight walk along x, with one tag and one point of interest beside it."""
    positions_m = np.column_stack([np.linspace(0.0, length_m, n), np.zeros(n), np.zeros(n)])
    return build_path_graph_from_arrays(
        positions_m,
        tag_ids=[1],
        tag_positions_m=[[0.0, 0.0, 0.5]],
        poi_names=["Kitchen"],
        poi_positions_m=[[length_m, 0.0, 0.5]],
    )


def test_a_poi_added_by_an_edit_is_in_the_figure():
    pg = make_corridor()
    edited = apply_edits(
        pg, [edit_from_json({"op": "add_poi", "name": "Water fountain", "at": [10.0, 0.0, 0.0]})]
    )
    assert all(outcome.applied for outcome in edited.outcomes)
    figure = {
        "tag_count": 1,
        "floors": [{"index": 0, "name": "Floor 1", "level_m": 0.0, "pois": [], "route": None}],
        "downsampled": None,
    }

    drawn = with_path_graph(figure, edited.path_graph)

    names = [poi["name"] for poi in drawn["floors"][0]["pois"]]
    assert sorted(names) == ["Kitchen", "Water fountain"]
    fountain = next(p for p in drawn["floors"][0]["pois"] if p["name"] == "Water fountain")
    assert (fountain["x"], fountain["z"]) == (10.0, 0.0)
    assert sorted(drawn["floors"][0]["nodes"]["id"]) == sorted(edited.path_graph.graph.nodes)
    assert figure["floors"][0]["pois"] == []  # a copy: the cached figure is not changed
    assert drawn["floors"][0]["name"] == "Floor 1"
