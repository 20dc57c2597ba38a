"""The app's earlier upload format (app.domain.upload.earlier_format): the three archive sessions
are read, a current session written in the earlier format reads back to the same arrays, and
sessions whose frames cannot be pinned down are refused naming the format."""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from app.domain.errors import SessionFormatError
from app.domain.mapping.slam import optimize_session
from app.domain.upload.earlier_format import EARLIER_FORMAT, is_earlier_format
from app.domain.upload.session import load_session, parse_session, read_json_document

ARCHIVE = Path(__file__).parents[2] / "data" / "archive"
SESSIONS = Path(__file__).parents[2] / "data" / "sessions"
#: file → (poses, detections, tags)
ARCHIVE_COUNTS = {"map": (2229, 354, 6), "round1": (2626, 261, 6), "round2": (1361, 129, 6)}


@pytest.mark.parametrize(("name", "counts"), sorted(ARCHIVE_COUNTS.items()))
def test_archive_sessions_are_read_and_make_maps(name, counts):
    session = load_session(ARCHIVE / f"{name}.json")
    assert (session.num_poses, len(session.detections), len(session.tag_ids)) == counts
    assert session.tag_ids == [6, 13, 18, 19, 22, 23]
    assert any(EARLIER_FORMAT in w for w in session.warnings)
    # every detection is attached to a pose within 0.1 s of it
    gap_s = np.abs(
        session.timestamp_s[session.detections.pose_index] - session.detections.timestamp_s
    )
    assert gap_s.max() <= 0.02
    # the frames hold: tags in front of the phone (−z), facing it
    p_phone = session.detections.phone_T_tag[:, :3, 3]
    assert np.all(p_phone[:, 2] < 0)
    result = optimize_session(session)
    assert len(result.tag_ids) == 6
    assert result.detections_used >= 0.9 * counts[1]


def earlier_rows(document: dict[str, Any], *, as_csv: bool, with_ids: bool) -> dict[str, Any]:
    """``document`` (current format, one detection per frame) written as the early app did."""
    time_of = {p["id"]: p["timestamp"] for p in document["pose_data"]}

    def row(values: list[float], prefix: str | None = None) -> Any:
        if as_csv:
            return ",".join(([prefix] if prefix else []) + [repr(float(v)) for v in values])
        return values

    poses = [
        row([*p["pose"], p["timestamp"], *([p["id"]] if with_ids else [])])
        for p in document["pose_data"]
    ]
    detections = [d for frame in document["tag_data"] for d in frame]
    tags = [
        row(
            [
                d["tag_id"],
                *d["tag_pose"],
                time_of[d["pose_id"]],
                *([d["pose_id"]] if with_ids else []),
            ],
            "TAG",
        )
        for d in detections
    ]
    fx, fy, cx, cy = detections[0]["camera_intrinsics"]
    return {
        "map_id": document["map_id"],
        "camera_intrinsics": f"{fx},{fy},{cx},{cy},1.000000,1920.000000,1440.000000",
        "pose_data": poses,
        "tag_data": tags,
    }


@pytest.mark.parametrize(("as_csv", "with_ids"), [(True, False), (False, False), (False, True)])
def test_a_session_in_the_earlier_format_reads_as_the_current_one(as_csv, with_ids):
    current = read_json_document(SESSIONS / "pgt_tester3.json")
    expected = parse_session(current)
    earlier = earlier_rows(current, as_csv=as_csv, with_ids=with_ids)
    assert is_earlier_format(earlier)
    assert not is_earlier_format(current)

    session = parse_session(earlier)

    assert session.map_id == expected.map_id
    np.testing.assert_allclose(session.world_T_phone, expected.world_T_phone, atol=1e-9)
    np.testing.assert_array_equal(session.detections.tag_id, expected.detections.tag_id)
    np.testing.assert_array_equal(session.detections.pose_index, expected.detections.pose_index)
    np.testing.assert_allclose(
        session.detections.phone_T_tag, expected.detections.phone_T_tag, atol=1e-9
    )
    if not with_ids:
        np.testing.assert_array_equal(session.pose_id, np.arange(expected.num_poses))


def refused(document: Any) -> SessionFormatError:
    with pytest.raises(SessionFormatError) as info:
        parse_session(document)
    assert EARLIER_FORMAT in str(info.value)
    return info.value


@pytest.fixture(scope="module")
def archive_round2() -> dict[str, Any]:
    return read_json_document(ARCHIVE / "round2.json")


def test_poses_that_are_not_column_major_are_refused_naming_the_format(archive_round2):
    document = copy.deepcopy(archive_round2)
    matrix = np.asarray(document["pose_data"][5][:16]).reshape(4, 4)
    document["pose_data"][5][:16] = matrix.T.reshape(16).tolist()  # written row-major
    error = refused(document)
    assert error.field == "pose_data[5]"
    assert "cannot be pinned down" in error.reason


def test_tags_behind_the_camera_are_refused_naming_the_format(archive_round2):
    document = copy.deepcopy(archive_round2)
    for row in document["tag_data"]:
        row[12] = -abs(row[12])  # z of camera_T_tag (row-major index 11, after the id)
    error = refused(document)
    assert error.field == "tag_data"
    assert "in front of the camera" in error.reason


@pytest.mark.parametrize(
    ("change", "field", "reason"),
    [
        (lambda d: d.pop("camera_intrinsics"), "camera_intrinsics", "missing"),
        (lambda d: d.update(camera_intrinsics="1,2"), "camera_intrinsics", "fx, fy"),
        (lambda d: d["pose_data"].__setitem__(3, "a,b,c"), "pose_data[3]", "not a row of numbers"),
        (lambda d: d["pose_data"].__setitem__(3, [1.0] * 5), "pose_data[3]", "got 5"),
        (lambda d: d["tag_data"].__setitem__(0, {"x": 1}), "tag_data[0]", "CSV string"),
        (lambda d: d["tag_data"][0].__setitem__(0, 2.5), "tag_data[0].tag_id", "id ≥ 0"),
        (lambda d: d["tag_data"][0].__setitem__(17, 1.0), "tag_data[0].timestamp", "no pose"),
        (lambda d: d.update(pose_data=[]), "pose_data", "empty session"),
    ],
)
def test_malformed_earlier_rows_name_the_field_and_the_format(
    archive_round2, change, field, reason
):
    document = copy.deepcopy(archive_round2)
    if field == "tag_data[0].timestamp":
        document["tag_data"][0] = document["tag_data"][0][:18]  # no pose id: matched by time
    change(document)
    error = refused(document)
    assert error.field == field
    assert reason in error.reason


@pytest.mark.parametrize(
    ("change", "field", "reason"),
    [
        (lambda d: d.pop("pose_data"), "pose_data", "missing"),
        (lambda d: d.update(pose_data={"x": 1}), "pose_data", "expected a list, got an object"),
        (
            lambda d: d.update(camera_intrinsics="1,2"),
            "camera_intrinsics",
            "expected fx, fy, cx, cy, …, got 2 numbers",
        ),
        (
            lambda d: d["tag_data"].__setitem__(0, {"x": 1}),
            "tag_data[0]",
            "expected a CSV string or an array of numbers, got an object",
        ),
        (
            lambda d: d["tag_data"].__setitem__(0, [True] * 18),
            "tag_data[0]",
            "expected a row of numbers",
        ),
        (
            lambda d: d["pose_data"][2].__setitem__(3, float("nan")),
            "pose_data[2]",
            "non-finite number",
        ),
        (
            lambda d: d["pose_data"].__setitem__(2, ",".join(["nan"] * 17)),
            "pose_data[2]",
            "non-finite number",
        ),
        (
            lambda d: d["tag_data"][0].__setitem__(0, -1),
            "tag_data[0].tag_id",
            "expected an id ≥ 0, got -1.0",
        ),
        (lambda d: d.update(pose_data=[]), "pose_data", "empty session: no poses"),
        (
            lambda d: d.pop("camera_intrinsics"),
            "camera_intrinsics",
            "missing: the earlier format keeps them at the top level",
        ),
        (
            lambda d: d.update(camera_intrinsics="a,b,c,d"),
            "camera_intrinsics",
            "not a row of numbers: could not convert string to float: 'a'",
        ),
        (
            lambda d: d["tag_data"].__setitem__(1, d["tag_data"][1][:17]),
            "tag_data[1]",
            "expected an id, 16 pose numbers, a timestamp and maybe a pose id, got 17",
        ),
        (
            lambda d: [row.__setitem__(12, -abs(row[12])) for row in d["tag_data"]],
            "tag_data",
            "only 0% of the detections are in front of the camera read as OpenCV camera_T_tag: "
            "the tags' frame cannot be pinned down",
        ),
    ],
)
def test_each_refusal_of_the_earlier_format_says_exactly_what_is_wrong(
    archive_round2, change, field, reason
):
    document = copy.deepcopy(archive_round2)
    change(document)
    error = refused(document)
    assert (error.field, error.reason) == (field, f"{reason} ({EARLIER_FORMAT})")
    assert str(error) == f"{field}: {reason} ({EARLIER_FORMAT})"


def test_tag_zero_is_an_id(archive_round2):
    document = copy.deepcopy(archive_round2)
    document["tag_data"][0][0] = 0
    session = parse_session(document)
    assert 0 in session.tag_ids


def test_csv_tag_rows_read_the_same_with_and_without_their_tag_prefix(archive_round2):
    def as_csv(row: list[float], prefix: str) -> str:
        return ",".join(([prefix] if prefix else []) + [repr(float(v)) for v in row])

    with_prefix = copy.deepcopy(archive_round2)
    with_prefix["tag_data"] = [as_csv(row, "TAG") for row in archive_round2["tag_data"]]
    without = copy.deepcopy(archive_round2)
    without["tag_data"] = [as_csv(row, "") for row in archive_round2["tag_data"]]

    expected = parse_session(archive_round2)
    for document in (with_prefix, without):
        session = parse_session(document)
        np.testing.assert_array_equal(session.detections.tag_id, expected.detections.tag_id)
        np.testing.assert_allclose(
            session.detections.phone_T_tag, expected.detections.phone_T_tag, atol=1e-12
        )


def test_an_earlier_session_says_how_it_was_read(archive_round2):
    session = parse_session(copy.deepcopy(archive_round2))
    notes = [w for w in session.warnings if "earlier format" in w]
    assert notes == [
        f"read from {EARLIER_FORMAT}",
        "tag corners projected from tag_pose (the earlier format has none): the reprojection "
        "check cannot reject a detection",
    ]


def test_an_earlier_session_without_tag_data_is_a_walk_without_tags(archive_round2):
    document = copy.deepcopy(archive_round2)
    del document["tag_data"]
    session = parse_session(document)
    assert session.num_poses == len(archive_round2["pose_data"])
    assert len(session.detections) == 0


def test_four_intrinsics_are_enough(archive_round2):
    document = copy.deepcopy(archive_round2)
    document["camera_intrinsics"] = ",".join(document["camera_intrinsics"].split(",")[:4])
    assert len(parse_session(document).detections) == len(archive_round2["tag_data"])


def test_a_tag_rows_pose_id_wins_over_the_nearest_pose_in_time(archive_round2):
    """A row of 19 numbers names its pose; only without a known pose id is it matched by time."""
    document = copy.deepcopy(archive_round2)
    pose_ids = [int(row[17]) for row in document["pose_data"]]
    row = document["tag_data"][0]
    nearest = parse_session(copy.deepcopy(document)).detections.pose_index[0]
    named = (nearest + 3) % len(pose_ids)  # another pose, 3 poses away
    document["tag_data"][0] = [*row[:18], pose_ids[named]]
    assert parse_session(document).detections.pose_index[0] == named
    document["tag_data"][0] = [*row[:18], max(pose_ids) + 1000]  # no such pose: by time
    assert parse_session(document).detections.pose_index[0] == nearest
