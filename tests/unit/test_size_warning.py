"""The tag-size warning is given where it matters, once per map, with what to do: when the tags
in the map disagree on their side, not when they all share one other than configured (the poses
are used as given) nor for a tag left out of the map."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from app.cli.common import DATA_DIR, DEMO_SESSIONS
from app.domain.mapping.params import SlamParams
from app.domain.mapping.screening import DetectionGeometry, _size_warnings, screen_detections
from app.domain.upload.session import load_session


def size_warnings(name: str) -> list[str]:
    session = load_session(DATA_DIR / "sessions" / f"{name}.json")
    warnings = screen_detections(session.detections, SlamParams()).warnings
    return [w for w in warnings if "tag side" in w]


def test_of_the_demo_walks_only_the_one_whose_tags_disagree_is_warned_once():
    warned = {name: size_warnings(name) for name, _ in DEMO_SESSIONS}
    # floor_2_straight, pgt_tester3 and singletag3times imply 0.150 m for every tag in the map
    # (floor_2's odd tag 323 is not in it); occam_room and desnat_straight_once 0.173 m.
    assert {name for name, lines in warned.items() if lines} == {"straight_209_occam"}
    (line,) = warned["straight_209_occam"]
    assert line.startswith(
        "6 tags' detections (tags 1, 2, 3, 4, 6, 7) imply a tag side of 0.170–0.174 m, "
        "the map's other 13 tags 0.150 m"
    )
    assert "Check that every tag is printed at one size" in line


def geometry(sides_m: list[float]) -> DetectionGeometry:
    n = len(sides_m)
    return DetectionGeometry(
        distance_m=np.ones(n),
        view_angle_deg=np.zeros(n),
        effective_size_m=np.array(sides_m),
        reprojection_px=np.zeros(n),
    )


@pytest.mark.parametrize(
    ("tag_ids", "sides_m", "used", "expected"),
    [
        # one odd tag: "tag 9's", not "1 tags'"
        (
            [1, 2, 3, 9],
            [0.15, 0.151, 0.149, 0.17],
            [True] * 4,
            "tag 9's detections imply a tag side of 0.170 m, the map's other 3 tags 0.150 m",
        ),
        # every tag at a side other than configured (0.173 m): nothing wrong with the map
        ([1, 2, 3], [0.15, 0.151, 0.149], [True] * 3, None),
        # the odd tag is not in the map (every detection of it rejected)
        ([1, 2, 3, 9], [0.15, 0.151, 0.149, 0.17], [True, True, True, False], None),
        # one tag alone has nothing to disagree with
        ([1, 1], [0.15, 0.151], [True, True], None),
    ],
)
def test_the_warning_names_the_odd_tags_in_the_map(tag_ids, sides_m, used, expected):
    detections = SimpleNamespace(tag_id=np.array(tag_ids))
    lines = _size_warnings(detections, geometry(sides_m), np.array(used))  # type: ignore[arg-type]
    if expected is None:
        assert lines == []
    else:
        (line,) = lines
        assert line.startswith(expected), line
