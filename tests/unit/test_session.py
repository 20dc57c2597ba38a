"""The upload parser (§2): typed arrays, the app's quirks, precise errors on bad input."""

from __future__ import annotations

import copy
import dataclasses
import gzip
import hashlib
import json
import math
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from app.domain.errors import NoTagsRecorded, SessionFormatError
from app.domain.upload.session import (
    NO_TAGS_REASON,
    Session,
    decode_json_bytes,
    first_observation_tag_poses,
    load_session,
    parse_session,
    require_tags,
)

DATA_DIR = Path(__file__).parents[2] / "data"
SESSIONS_DIR = DATA_DIR / "sessions"

#: The OpenCV camera frame (y down, z forward) seen from the ARKit phone frame (y up, −z forward).
PHONE_T_CAMERA_CV = np.diag([1.0, -1.0, -1.0, 1.0])
TAG_SIZE_M = 0.173


# --------------------------------------------------------------------------- builders


def rot_x(angle_rad: float) -> np.ndarray:
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(angle_rad: float) -> np.ndarray:
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(angle_rad: float) -> np.ndarray:
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def pose(R: np.ndarray, t: Sequence[float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def column_major(T: np.ndarray) -> list[float]:
    """ARKit's flattening: column by column, translation at 12–14."""
    return [float(v) for v in T.flatten(order="F")]


def row_major(T: np.ndarray) -> list[float]:
    return [float(v) for v in T.flatten(order="C")]


def default_world_T_phone(i: int) -> np.ndarray:
    """A walk with turns and a tilt, so that a transposed reading would not go unnoticed."""
    return pose(rot_y(0.3 * i) @ rot_x(0.1), [0.5 * i, 0.05 * i, -0.2 * i])


#: A tag 1.2 m ahead of the camera, rotated so that no axis lines up with the camera's.
DEFAULT_CAMERA_T_TAG = pose(
    rot_x(0.3) @ rot_y(0.2) @ rot_z(0.1) @ np.diag([1.0, -1.0, -1.0]), [0.1, -0.05, 1.2]
)


def project_corners(camera_T_tag: np.ndarray, intrinsics: Sequence[float]) -> list[float]:
    fx, fy, cx, cy = intrinsics
    half = TAG_SIZE_M / 2
    corners: list[float] = []
    for x, y in ((-half, -half), (half, -half), (half, half), (-half, half)):
        X, Y, Z, _ = camera_T_tag @ np.array([x, y, 0.0, 1.0])
        corners += [fx * X / Z + cx, fy * Y / Z + cy]
    return corners


def make_detection(
    *,
    tag_id: int = 0,
    pose_id: int = 0,
    timestamp: float | None = None,
    camera_T_tag: np.ndarray | None = None,
    intrinsics: Sequence[float] = (1500.0, 1510.0, 960.0, 720.0),
) -> dict[str, Any]:
    """One entry of a ``tag_data`` frame, as the app writes it."""
    camera_T_tag = DEFAULT_CAMERA_T_TAG if camera_T_tag is None else camera_T_tag
    return {
        "tag_id": tag_id,
        "pose_id": pose_id,
        "timestamp": 100.0 + 0.5 * pose_id if timestamp is None else timestamp,
        "tag_pose": row_major(camera_T_tag),
        "camera_intrinsics": list(intrinsics),
        "tag_corners_pixel_coordinates": project_corners(camera_T_tag, intrinsics),
        "tag_position_variance": [1e-6, 2e-6, 3e-6],
        "tag_orientation_variance": [1e-3, 2e-3, 3e-3, 4e-3],
        "joint_covar": [1e-6 * k for k in range(49)],
    }


def make_location(name: str, pose_id: int, phone_T_poi: np.ndarray | None = None) -> dict[str, Any]:
    phone_T_poi = pose(rot_y(0.5), [0.0, 0.0, -1.0]) if phone_T_poi is None else phone_T_poi
    return {
        "name": name,
        "pose_id": pose_id,
        "timestamp": 100.0 + 0.5 * pose_id,
        "transform": row_major(phone_T_poi),
    }


def make_upload(
    num_poses: int = 5,
    frames: list[list[dict[str, Any]]] | None = None,
    *,
    locations: list[dict[str, Any]] | None = None,
    world_T_phone: Sequence[np.ndarray] | None = None,
    first_pose_id: int = 0,
    step_s: float = 0.5,
) -> dict[str, Any]:
    """A session in the app's upload format.

    By default: 5 poses; frame 0 holds tag 3 seen from pose 1, frame 1 holds tags 4 and 5 both seen
    from pose 2 (a two-detection frame).
    """
    if world_T_phone is None:
        world_T_phone = [default_world_T_phone(i) for i in range(num_poses)]
    if frames is None:
        frames = [
            [make_detection(tag_id=3, pose_id=first_pose_id + 1)],
            [
                make_detection(tag_id=4, pose_id=first_pose_id + 2),
                make_detection(tag_id=5, pose_id=first_pose_id + 2),
            ],
        ]
    return {
        "map_id": "test-session",
        "pose_data": [
            {
                "id": first_pose_id + i,
                "timestamp": 100.0 + step_s * i,
                "pose": column_major(T),
                "planes": [],
            }
            for i, T in enumerate(world_T_phone)
        ],
        "tag_data": frames,
        "location_data": [] if locations is None else locations,
        "plane_data": [],
    }


def assert_format_error(document: Any, field: str, *reason_parts: str) -> SessionFormatError:
    """``parse_session(document)`` fails naming ``field``, with every part in the reason."""
    with pytest.raises(SessionFormatError) as info:
        parse_session(document)
    return check_format_error(info.value, field, *reason_parts)


def check_format_error(
    err: SessionFormatError, field: str, *reason_parts: str
) -> SessionFormatError:
    assert err.field == field
    if field:
        assert str(err).startswith(f"{field}: ")
    for part in reason_parts:
        assert part in err.reason, f"{part!r} not in {err.reason!r}"
    assert "\n" not in str(err)
    return err


# --------------------------------------------------------------------------- a valid session


def test_builder_session_counts_and_ids():
    session = parse_session(make_upload())
    assert isinstance(session, Session)
    assert session.map_id == "test-session"
    assert session.num_poses == 5
    np.testing.assert_array_equal(session.pose_id, [0, 1, 2, 3, 4])
    np.testing.assert_allclose(session.timestamp_s, [100.0, 100.5, 101.0, 101.5, 102.0])
    assert len(session.detections) == 3
    assert session.tag_ids == [3, 4, 5]
    np.testing.assert_array_equal(session.detections.tag_id, [3, 4, 5])
    np.testing.assert_array_equal(session.detections.pose_index, [1, 2, 2])
    assert session.warnings == ()
    assert session.pois == ()
    assert str(session).startswith("test-session: 5 poses")


def test_pose_is_read_column_major():
    world_T_phone = [default_world_T_phone(i) for i in range(4)]
    world_T_phone[2] = pose(rot_z(0.7) @ rot_x(-0.4), [1.0, 2.0, 3.0])
    document = make_upload(4, frames=[], world_T_phone=world_T_phone)
    # The app's layout: translation at indices 12..14.
    assert document["pose_data"][2]["pose"][12:15] == [1.0, 2.0, 3.0]

    session = parse_session(document)

    np.testing.assert_allclose(session.world_T_phone[2][:3, 3], [1.0, 2.0, 3.0], atol=1e-12)
    np.testing.assert_allclose(session.world_T_phone[2], world_T_phone[2], atol=1e-12)
    np.testing.assert_allclose(session.world_T_phone, np.stack(world_T_phone), atol=1e-12)
    assert session.world_T_phone.shape == (4, 4, 4)
    assert session.world_T_phone.dtype == np.float64


def test_tag_pose_is_read_row_major_and_turned_into_the_phone_frame():
    session = parse_session(make_upload())
    detections = session.detections

    assert detections.camera_T_tag.shape == (3, 4, 4)
    np.testing.assert_allclose(detections.camera_T_tag[0], DEFAULT_CAMERA_T_TAG, atol=1e-12)
    np.testing.assert_allclose(detections.camera_T_tag[0][:3, 3], [0.1, -0.05, 1.2], atol=1e-12)
    # OpenCV (y down, z forward) to ARKit (y up, looking along −z).
    np.testing.assert_allclose(
        detections.phone_T_tag[0], PHONE_T_CAMERA_CV @ DEFAULT_CAMERA_T_TAG, atol=1e-12
    )
    np.testing.assert_allclose(detections.phone_T_tag[0][:3, 3], [0.1, 0.05, -1.2], atol=1e-12)


def test_world_T_tag_observed_composes_odometry_and_detection():
    session = parse_session(make_upload())
    world_T_tag = session.world_T_tag_observed()

    assert world_T_tag.shape == (3, 4, 4)
    for row, pose_index in enumerate([1, 2, 2]):
        expected = default_world_T_phone(pose_index) @ PHONE_T_CAMERA_CV @ DEFAULT_CAMERA_T_TAG
        np.testing.assert_allclose(world_T_tag[row], expected, atol=1e-12)
    first = first_observation_tag_poses(session)
    assert sorted(first) == [3, 4, 5]
    np.testing.assert_allclose(first[4], world_T_tag[1], atol=1e-12)


def test_frame_index_and_frame_size():
    frames = [
        [make_detection(tag_id=3, pose_id=1)],
        [make_detection(tag_id=4, pose_id=2), make_detection(tag_id=5, pose_id=2)],
        [make_detection(tag_id=3, pose_id=4)],
    ]
    detections = parse_session(make_upload(frames=frames)).detections

    np.testing.assert_array_equal(detections.frame_index, [0, 1, 1, 2])
    np.testing.assert_array_equal(detections.frame_size, [1, 2, 2, 1])
    np.testing.assert_array_equal(detections.pose_index, [1, 2, 2, 4])


def test_detection_vectors_keep_their_layout():
    document = make_upload()
    raw = document["tag_data"][0][0]
    detections = parse_session(document).detections

    np.testing.assert_allclose(detections.intrinsics[0], [1500.0, 1510.0, 960.0, 720.0])
    assert detections.corners_px.shape == (3, 4, 2)
    np.testing.assert_allclose(
        detections.corners_px[0], np.reshape(raw["tag_corners_pixel_coordinates"], (4, 2))
    )
    # Corner 1 is (+s/2, −s/2): right of corner 0 in the image, same row up to perspective.
    assert detections.corners_px[0, 1, 0] != detections.corners_px[0, 0, 0]
    np.testing.assert_allclose(detections.position_variance_m2[0], [1e-6, 2e-6, 3e-6])
    np.testing.assert_allclose(detections.orientation_variance[0], [1e-3, 2e-3, 3e-3, 4e-3])
    assert detections.joint_covariance.shape == (3, 7, 7)
    # Row-major 7×7: element [0, 1] is entry 1, [1, 0] is entry 7.
    assert detections.joint_covariance[0, 0, 1] == pytest.approx(1e-6)
    assert detections.joint_covariance[0, 1, 0] == pytest.approx(7e-6)
    np.testing.assert_allclose(detections.timestamp_s, [100.5, 101.0, 101.0])


def test_missing_optional_detection_fields_become_nan():
    detection = make_detection(tag_id=1, pose_id=0)
    for key in ("tag_position_variance", "tag_orientation_variance", "joint_covar", "timestamp"):
        del detection[key]
    detections = parse_session(make_upload(frames=[[detection]])).detections

    assert np.isnan(detections.position_variance_m2).all()
    assert detections.position_variance_m2.shape == (1, 3)
    assert np.isnan(detections.orientation_variance).all()
    assert np.isnan(detections.joint_covariance).all()
    assert np.isnan(detections.timestamp_s[0])


def test_pose_ids_need_not_start_at_zero():
    document = make_upload(first_pose_id=10)
    session = parse_session(document)

    np.testing.assert_array_equal(session.pose_id, [10, 11, 12, 13, 14])
    # pose_index is the row in the pose arrays, not the app's id.
    np.testing.assert_array_equal(session.detections.pose_index, [1, 2, 2])


def test_poi_pose_id_off_by_one_is_corrected_by_default():
    phone_T_poi = pose(rot_y(0.5), [0.2, 0.0, -1.0])
    document = make_upload(locations=[make_location("  Room 209 ", 3, phone_T_poi)])

    corrected = parse_session(document)
    as_written = parse_session(document, correct_poi_pose_id=False)

    assert len(corrected.pois) == 1
    poi = corrected.pois[0]
    assert poi.name == "Room 209"
    assert poi.pose_index == 2  # the app's pose_id 3 points to the next pose
    assert as_written.pois[0].pose_index == 3
    np.testing.assert_allclose(poi.phone_T_poi, phone_T_poi, atol=1e-12)  # row-major
    assert poi.timestamp_s == pytest.approx(101.5)


def test_load_session_passes_poi_correction_through(tmp_path):
    path = tmp_path / "poi.json"
    path.write_text(json.dumps(make_upload(locations=[make_location("door", 4)])))

    assert load_session(path).pois[0].pose_index == 3
    assert load_session(path, correct_poi_pose_id=False).pois[0].pose_index == 4


def test_poi_at_the_last_pose_only_exists_without_correction():
    document = make_upload(locations=[make_location("end", 0)])

    assert parse_session(document, correct_poi_pose_id=False).pois[0].pose_index == 0
    err = assert_format_error(document, "location_data[0].pose_id", "no pose with id -1")
    assert "off-by-one" in err.reason


def test_path_length_is_the_sum_of_steps():
    session = parse_session(make_upload(3, frames=[]))
    step = math.sqrt(0.5**2 + 0.05**2 + 0.2**2)
    assert session.path_length_m() == pytest.approx(2 * step)


def test_session_without_detections_parses_with_a_warning():
    session = parse_session(make_upload(frames=[]))

    assert len(session.detections) == 0
    assert session.tag_ids == []
    assert session.detections.phone_T_tag.shape == (0, 4, 4)
    assert session.detections.corners_px.shape == (0, 4, 2)
    assert session.world_T_tag_observed().shape == (0, 4, 4)
    assert len(session.warnings) == 1
    assert session.warnings[0] == NO_TAGS_REASON


def test_session_with_empty_frames_has_no_detections():
    session = parse_session(make_upload(frames=[[], []]))
    assert len(session.detections) == 0
    assert session.warnings


@pytest.mark.parametrize("frames", [[], [[], []]])
def test_no_detections_have_the_layout_of_detections(frames):
    """A session without sightings has every detection array as one with sightings has it, only
    empty: the same trailing shape and the same dtype (the solver, the stores and the stream
    parser concatenate and index them alike)."""
    seen = parse_session(make_upload()).detections
    none = parse_session(make_upload(frames=frames)).detections
    for field in dataclasses.fields(type(seen)):
        empty, full = getattr(none, field.name), getattr(seen, field.name)
        assert empty.shape == (0, *full.shape[1:]), field.name
        assert empty.dtype == full.dtype, field.name


def test_single_detection_session():
    session = parse_session(make_upload(2, frames=[[make_detection(tag_id=7, pose_id=1)]]))

    assert len(session.detections) == 1
    assert session.tag_ids == [7]
    assert session.warnings == ()
    np.testing.assert_array_equal(session.detections.frame_size, [1])
    assert session.world_T_tag_observed().shape == (1, 4, 4)


def test_single_pose_session():
    session = parse_session(make_upload(1, frames=[[make_detection(tag_id=0, pose_id=0)]]))
    assert session.num_poses == 1
    assert session.path_length_m() == 0.0


def test_nearly_rigid_float32_pose_is_orthonormalized():
    T = default_world_T_phone(2)
    document = make_upload(3, frames=[])
    document["pose_data"][2]["pose"] = [float(np.float32(v)) for v in column_major(T)]

    world_T_phone = parse_session(document).world_T_phone[2]

    R = world_T_phone[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(world_T_phone, T, atol=1e-6)


# --------------------------------------------------------------------------- real sessions

REAL_SESSIONS = {
    # file: (poses, tag detections, distinct tags), from data/README.md
    "occam_room.json": (621, 200, 8),
    "floor_2_straight.json": (1004, 54, 25),
    "straight_209_occam.json": (1007, 150, 20),
    "desnat_straight_once.json": (604, 79, 8),
    "pgt_tester3.json": (132, 10, 4),
    "singletag3times.json": (63, 4, 1),
    "onetag.json": (25, 1, 1),
}


def test_every_real_session_is_in_the_table():
    assert sorted(p.name for p in SESSIONS_DIR.glob("*.json")) == sorted(REAL_SESSIONS)


@pytest.mark.parametrize(("name", "counts"), sorted(REAL_SESSIONS.items()))
def test_real_session_parses_with_documented_counts(name, counts):
    poses, detections, tags = counts
    session = load_session(SESSIONS_DIR / name)

    assert session.num_poses == poses
    assert len(session.detections) == detections
    assert len(session.tag_ids) == tags
    assert session.warnings == ()
    assert np.all(np.diff(session.pose_id) > 0)
    assert np.all(np.diff(session.timestamp_s) >= 0)
    assert np.isfinite(session.world_T_tag_observed()).all()
    R = session.world_T_phone[:, :3, :3]
    np.testing.assert_allclose(
        R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-9
    )


def test_real_session_tag_ids_match_the_readme():
    assert load_session(SESSIONS_DIR / "occam_room.json").tag_ids == list(range(8))
    assert load_session(SESSIONS_DIR / "floor_2_straight.json").tag_ids == list(range(300, 325))
    assert load_session(SESSIONS_DIR / "desnat_straight_once.json").tag_ids == list(range(300, 308))


def test_real_session_reads_the_same_gzipped(tmp_path):
    raw = (SESSIONS_DIR / "pgt_tester3.json").read_bytes()
    path = tmp_path / "pgt_tester3.json.gz"
    path.write_bytes(gzip.compress(raw))

    plain = load_session(SESSIONS_DIR / "pgt_tester3.json")
    zipped = load_session(path)

    np.testing.assert_array_equal(zipped.world_T_phone, plain.world_T_phone)
    np.testing.assert_array_equal(zipped.detections.phone_T_tag, plain.detections.phone_T_tag)


# --------------------------------------------------------------------------- quirks accepted


def test_unknown_keys_are_accepted_everywhere():
    document = make_upload(locations=[make_location("desk", 2)])
    document["app_version"] = "1.2.3"
    document["pose_data"][0]["tracking_state"] = "normal"
    document["tag_data"][0][0]["future_field"] = {"nested": [1, 2]}
    document["location_data"][0]["color"] = "red"

    session = parse_session(document)
    assert len(session.detections) == 3
    assert len(session.pois) == 1


def test_orig_pose_on_detection_is_accepted_and_ignored():
    document = make_upload()
    document["tag_data"][0][0]["orig_pose"] = [0.0] * 16  # not even a rigid transform
    session = parse_session(document)
    np.testing.assert_allclose(session.detections.camera_T_tag[0], DEFAULT_CAMERA_T_TAG, atol=1e-12)


def test_planes_and_plane_data_are_accepted():
    document = make_upload()
    document["pose_data"][1]["planes"] = [{"id": 1, "transform": [1, 2, 3]}]
    document["plane_data"] = [{"id": 1, "boundaries": [[0, 0], [1, 1]]}]
    assert parse_session(document).num_poses == 5


def test_missing_tag_data_location_data_and_plane_data_are_accepted():
    document = make_upload()
    for key in ("tag_data", "location_data", "plane_data"):
        del document[key]
    session = parse_session(document)
    assert len(session.detections) == 0
    assert session.pois == ()


def test_null_location_data_is_accepted():
    document = make_upload()
    document["location_data"] = None
    assert parse_session(document).pois == ()


def test_misspelt_location_key_is_read():
    document = make_upload()
    del document["location_data"]
    document["location_ data"] = [make_location("kitchen", 3)]

    session = parse_session(document)

    assert [poi.name for poi in session.pois] == ["kitchen"]
    assert session.pois[0].pose_index == 2


def test_error_in_misspelt_location_key_names_that_key():
    document = make_upload()
    del document["location_data"]
    document["location_ data"] = [make_location("", 3)]
    document["location_ data"][0]["name"] = None
    assert_format_error(document, "location_ data[0].name", "missing")


def test_bare_detection_in_place_of_a_frame_is_accepted():
    document = make_upload()
    document["tag_data"] = [make_detection(tag_id=9, pose_id=3)]
    detections = parse_session(document).detections
    np.testing.assert_array_equal(detections.tag_id, [9])
    np.testing.assert_array_equal(detections.frame_size, [1])


def test_integral_floats_are_accepted_as_ids():
    document = make_upload()
    document["tag_data"][0][0]["tag_id"] = 3.0
    document["pose_data"][4]["id"] = 4.0
    session = parse_session(document)
    assert session.tag_ids == [3, 4, 5]
    assert session.pose_id[4] == 4


def test_gzip_bytes_are_decoded():
    document = make_upload()
    raw = json.dumps(document).encode()

    assert decode_json_bytes(gzip.compress(raw)) == decode_json_bytes(raw) == document
    session = parse_session(decode_json_bytes(gzip.compress(raw)))
    assert len(session.detections) == 3


def test_load_session_reads_gzip_file(tmp_path):
    path = tmp_path / "upload.json.gz"
    path.write_bytes(gzip.compress(json.dumps(make_upload()).encode()))
    assert load_session(path).num_poses == 5


# --------------------------------------------------------------------------- bad bytes


def test_non_json_bytes():
    with pytest.raises(SessionFormatError) as info:
        decode_json_bytes(b"hello, not json", source="upload.json")
    check_format_error(info.value, "", "upload.json", "not valid JSON", "line 1")


def test_truncated_real_file():
    raw = (SESSIONS_DIR / "onetag.json").read_bytes()
    with pytest.raises(SessionFormatError) as info:
        decode_json_bytes(raw[: len(raw) // 2])
    check_format_error(info.value, "", "not valid JSON", "line")


def test_truncated_real_file_on_disk(tmp_path):
    raw = (SESSIONS_DIR / "onetag.json").read_bytes()
    path = tmp_path / "cut.json"
    path.write_bytes(raw[: len(raw) // 2])
    with pytest.raises(SessionFormatError) as info:
        load_session(path)
    check_format_error(info.value, "", str(path), "not valid JSON")


def test_truncated_gzip():
    packed = gzip.compress(json.dumps(make_upload()).encode())
    with pytest.raises(SessionFormatError) as info:
        decode_json_bytes(packed[: len(packed) // 2])
    check_format_error(info.value, "", "not valid gzip")


def test_not_utf8():
    with pytest.raises(SessionFormatError) as info:
        decode_json_bytes(b'{"map_id": "\xff\xfe"}')
    check_format_error(info.value, "", "not UTF-8")


def test_empty_bytes():
    with pytest.raises(SessionFormatError, match="not valid JSON"):
        decode_json_bytes(b"")


def test_deeply_nested_json_is_a_format_error():
    # A hostile upload: far deeper than any session, must not escape as RecursionError.
    with pytest.raises(SessionFormatError) as info:
        decode_json_bytes(b"[" * 100_000 + b"]" * 100_000, source="upload.json")
    check_format_error(info.value, "", "upload.json is nested too deeply to be a session")


def test_an_integer_of_too_many_digits_is_not_valid_json():
    with pytest.raises(SessionFormatError) as info:
        decode_json_bytes(b'{"map_id": ' + b"9" * 5000 + b"}", source="upload.json")
    check_format_error(info.value, "", "upload.json is not valid JSON: Exceeds the limit")
    assert "sys.set_int_max_str_digits" not in info.value.reason  # the advice after ';' is cut


def test_missing_file(tmp_path):
    with pytest.raises(SessionFormatError) as info:
        load_session(tmp_path / "nope.json")
    check_format_error(info.value, "", "cannot read", "nope.json")
    assert info.value.reason == f"cannot read {tmp_path / 'nope.json'}: No such file or directory"


def test_nan_and_infinity_tokens_in_json_are_rejected():
    document = make_upload()
    document["pose_data"][1]["pose"][4] = math.nan
    raw = json.dumps(document).encode()
    assert b"NaN" in raw  # Python's json writes and reads these tokens
    with pytest.raises(SessionFormatError) as info:
        parse_session(decode_json_bytes(raw))
    check_format_error(info.value, "pose_data[1].pose[4]", "non-finite")

    document = make_upload()
    document["tag_data"][1][1]["tag_pose"][3] = -math.inf
    raw = json.dumps(document).encode()
    assert b"-Infinity" in raw
    with pytest.raises(SessionFormatError) as info:
        parse_session(decode_json_bytes(raw))
    check_format_error(info.value, "tag_data[1][1].tag_pose[3]", "non-finite")


# --------------------------------------------------------------------------- bad documents


def test_not_an_object():
    assert_format_error([make_upload()], "", "expected a JSON object", "list")
    assert_format_error("session", "", "expected a JSON object", "string")
    assert_format_error(None, "", "expected a JSON object", "null")


def test_missing_map_id():
    document = make_upload()
    del document["map_id"]
    assert_format_error(document, "map_id", "missing")


@pytest.mark.parametrize(
    ("map_id", "reason"), [(17, "a number"), (None, "missing"), (["a"], "a list")]
)
def test_bad_map_id(map_id, reason):
    document = make_upload()
    document["map_id"] = map_id
    assert_format_error(document, "map_id", reason)


@pytest.mark.parametrize("map_id", ["", "   "])
def test_empty_map_id_is_named_from_the_upload_stably(map_id):
    """The app sets map_id to the typed name, which may be empty: the walk is kept, named from
    its poses (the same walk always gets the same name, another walk another)."""
    document = make_upload()
    document["map_id"] = map_id
    session = parse_session(document)
    assert session.map_id.startswith("unnamed-")
    assert parse_session(copy.deepcopy(document)).map_id == session.map_id
    assert any("map_id was empty" in w and session.map_id in w for w in session.warnings)
    other = make_upload(9)
    other["map_id"] = ""
    assert parse_session(other).map_id != session.map_id


def test_the_name_of_an_unnamed_walk_is_a_digest_of_its_times_and_places():
    """The name is kept with the map and must not change between releases: the first 10 hex
    digits of SHA-256 over the poses' times, then their positions (x, y, z, float64)."""
    document = make_upload()
    document["map_id"] = ""
    times = np.array([p["timestamp"] for p in document["pose_data"]], dtype=np.float64)
    places = np.array([p["pose"][12:15] for p in document["pose_data"]], dtype=np.float64)
    digest = hashlib.sha256(times.tobytes() + places.tobytes()).hexdigest()
    assert parse_session(document).map_id == f"unnamed-{digest[:10]}"


def test_a_walk_without_tags_is_refused_a_map_and_one_tag_seen_once_is_enough():
    no_tags = parse_session(make_upload(frames=[]))
    with pytest.raises(NoTagsRecorded) as info:
        require_tags(no_tags)
    assert (
        str(info.value) == NO_TAGS_REASON == "no tags were recorded: a map needs at least one tag"
    )
    one_sighting = parse_session(make_upload(frames=[[make_detection(tag_id=3, pose_id=1)]]))
    assert len(one_sighting.detections) == 1
    require_tags(one_sighting)  # no error


def test_empty_poi_names_get_stable_generated_names_and_are_reported():
    document = make_upload(
        locations=[
            make_location("", 2),
            make_location("Kitchen", 3),
            make_location("   ", 4),
            make_location("Point 3", 4),
            make_location("Kitchen", 5),
            make_location("Point 3 (2)", 5),
        ]
    )
    session = parse_session(document)
    assert [p.name for p in session.pois] == [
        "Point 1",
        "Kitchen",
        "Point 3 (3)",  # "Point 3" and "Point 3 (2)" are someone's names already
        "Point 3",
        "Kitchen",
        "Point 3 (2)",
    ]
    assert [w for w in session.warnings if "location_data" in w or "points of interest" in w] == [
        "location_data[0].name was empty: named 'Point 1'",
        "location_data[2].name was empty: named 'Point 3 (3)'",
        "2 points of interest are named 'Kitchen'",
    ]
    assert [p.name for p in parse_session(document).pois] == [p.name for p in session.pois]


@pytest.mark.parametrize(("name", "reason"), [(None, "missing"), (7, "a number")])
def test_poi_name_must_still_be_a_string(name, reason):
    document = make_upload(locations=[make_location("x", 2)])
    document["location_data"][0]["name"] = name
    assert_format_error(document, "location_data[0].name", reason)


def test_missing_pose_data():
    document = make_upload()
    del document["pose_data"]
    assert_format_error(document, "pose_data", "missing")


def test_pose_data_not_a_list():
    document = make_upload()
    document["pose_data"] = {"0": document["pose_data"][0]}
    assert_format_error(document, "pose_data", "expected a list", "object")


def test_empty_pose_data():
    document = make_upload(frames=[])
    document["pose_data"] = []
    assert_format_error(document, "pose_data", "empty session")


def test_pose_entry_not_an_object():
    document = make_upload()
    document["pose_data"][3] = [1, 2, 3]
    assert_format_error(document, "pose_data[3]", "expected an object", "list")


def test_pose_with_15_numbers():
    document = make_upload()
    document["pose_data"][2]["pose"] = document["pose_data"][2]["pose"][:15]
    assert_format_error(document, "pose_data[2].pose", "16", "15")


def test_pose_as_4_rows():
    document = make_upload()
    document["pose_data"][2]["pose"] = default_world_T_phone(2).tolist()
    assert_format_error(document, "pose_data[2].pose", "16", "4 rows")


def test_pose_missing():
    document = make_upload()
    del document["pose_data"][1]["pose"]
    assert_format_error(document, "pose_data[1].pose", "missing")


def test_nan_in_pose():
    document = make_upload()
    document["pose_data"][2]["pose"][12] = math.nan
    assert_format_error(document, "pose_data[2].pose[12]", "non-finite")


def test_infinity_in_tag_pose():
    document = make_upload()
    document["tag_data"][0][0]["tag_pose"][7] = math.inf
    assert_format_error(document, "tag_data[0][0].tag_pose[7]", "non-finite")


def test_a_pose_beyond_100_km_is_refused():
    document = make_upload()
    document["pose_data"][2]["pose"][14] = -2e5  # column-major: z translation
    assert_format_error(document, "pose_data[2].pose", "translation", "beyond 100000 m")


def test_a_tag_beyond_100_km_of_the_camera_is_refused():
    document = make_upload()
    document["tag_data"][0][0]["tag_pose"][3] = 1e300  # row-major: x translation
    assert_format_error(document, "tag_data[0][0].tag_pose", "beyond 100000 m")


@pytest.mark.parametrize(
    ("key", "index"), [("camera_intrinsics", 0), ("camera_intrinsics", 3),
                       ("tag_corners_pixel_coordinates", 5)],
)  # fmt: skip
def test_pixels_beyond_100000_are_refused(key, index):
    document = make_upload()
    document["tag_data"][0][0][key][index] = -1e200 if index else 1e200
    assert_format_error(document, f"tag_data[0][0].{key}[{index}]", "beyond 100000 px")


def test_string_in_matrix():
    document = make_upload()
    document["pose_data"][1]["pose"][5] = "0.5"
    assert_format_error(document, "pose_data[1].pose[5]", "expected a number", "string")


def test_null_in_matrix():
    document = make_upload()
    document["tag_data"][1][0]["tag_pose"][0] = None
    assert_format_error(document, "tag_data[1][0].tag_pose[0]", "expected a number", "null")


def test_scaled_rotation_is_not_orthonormal():
    T = default_world_T_phone(2)
    T[:3, :3] *= 1.5
    document = make_upload()
    document["pose_data"][2]["pose"] = column_major(T)
    assert_format_error(document, "pose_data[2].pose", "not orthonormal")


def test_scaled_tag_rotation_is_not_orthonormal():
    T = DEFAULT_CAMERA_T_TAG.copy()
    T[:3, :3] *= 1.5
    document = make_upload()
    document["tag_data"][1][1]["tag_pose"] = row_major(T)
    assert_format_error(document, "tag_data[1][1].tag_pose", "not orthonormal")


def test_reflection_is_rejected():
    T = default_world_T_phone(1)
    T[:3, 0] *= -1  # orthonormal, determinant −1
    document = make_upload()
    document["pose_data"][1]["pose"] = column_major(T)
    assert_format_error(document, "pose_data[1].pose", "reflection")


def test_bad_last_row_is_rejected():
    T = default_world_T_phone(1)
    T[3] = [0.0, 0.0, 1.0, 1.0]
    document = make_upload()
    document["pose_data"][1]["pose"] = column_major(T)
    assert_format_error(document, "pose_data[1].pose", "last row")


def test_transposed_pose_with_translation_in_last_row_is_rejected():
    # A row-major pose where column-major is expected puts the translation in the last row.
    T = default_world_T_phone(3)
    document = make_upload()
    document["pose_data"][3]["pose"] = row_major(T)
    assert_format_error(document, "pose_data[3].pose", "last row")


def test_tag_pose_id_with_no_pose():
    document = make_upload()
    document["tag_data"][0][0]["pose_id"] = 5
    assert_format_error(document, "tag_data[0][0].pose_id", "no pose", "5")


def test_tag_pose_id_with_no_pose_in_second_detection_of_a_frame():
    document = make_upload()
    document["tag_data"][1][1]["pose_id"] = -1
    assert_format_error(document, "tag_data[1][1].pose_id", "no pose", "-1")


def test_negative_tag_id():
    document = make_upload()
    document["tag_data"][1][0]["tag_id"] = -3
    assert_format_error(document, "tag_data[1][0].tag_id", "-3")


def test_fractional_tag_id():
    document = make_upload()
    document["tag_data"][0][0]["tag_id"] = 3.5
    assert_format_error(document, "tag_data[0][0].tag_id", "expected an integer", "3.5")


def test_pose_ids_not_increasing():
    document = make_upload()
    document["pose_data"][3]["id"] = 2
    assert_format_error(document, "pose_data[3].id", "must increase", "2 follows 2")


def test_pose_ids_decreasing():
    document = make_upload()
    document["pose_data"][4]["id"] = 1
    assert_format_error(document, "pose_data[4].id", "must increase")


def test_timestamps_going_backwards():
    document = make_upload()
    document["pose_data"][3]["timestamp"] = 100.2
    assert_format_error(document, "pose_data[3].timestamp", "backwards")


def test_equal_timestamps_are_accepted():
    document = make_upload()
    document["pose_data"][3]["timestamp"] = document["pose_data"][2]["timestamp"]
    assert parse_session(document).num_poses == 5


def test_timestamp_not_a_number():
    document = make_upload()
    document["pose_data"][2]["timestamp"] = "12:00"
    assert_format_error(document, "pose_data[2].timestamp", "expected a number", "string")


def test_bool_where_int_expected():
    document = make_upload()
    document["tag_data"][0][0]["tag_id"] = True
    assert_format_error(document, "tag_data[0][0].tag_id", "expected an integer", "boolean")

    document = make_upload()
    document["pose_data"][1]["id"] = True
    assert_format_error(document, "pose_data[1].id", "expected an integer", "boolean")


def test_bool_in_matrix():
    document = make_upload()
    document["pose_data"][0]["pose"][15] = True
    assert_format_error(document, "pose_data[0].pose[15]", "expected a number", "boolean")


def test_poi_whose_corrected_pose_id_has_no_pose():
    document = make_upload(locations=[make_location("lab", 2), make_location("exit", 0)])
    assert_format_error(document, "location_data[1].pose_id", "no pose with id -1")


def test_poi_pose_id_beyond_the_last_pose():
    document = make_upload(locations=[make_location("lab", 9)])
    assert_format_error(document, "location_data[0].pose_id", "no pose with id 8")


def test_poi_transform_checked():
    location = make_location("lab", 2)
    location["transform"] = location["transform"][:12]
    document = make_upload(locations=[location])
    assert_format_error(document, "location_data[0].transform", "16", "12")


def test_location_data_not_a_list():
    document = make_upload()
    document["location_data"] = {"name": "lab"}
    assert_format_error(document, "location_data", "expected a list", "object")


@pytest.mark.parametrize("index", [0, 1])
def test_zero_focal_length(index):
    document = make_upload()
    document["tag_data"][1][0]["camera_intrinsics"][index] = 0.0
    assert_format_error(document, "tag_data[1][0].camera_intrinsics", "focal")


def test_intrinsics_wrong_length():
    document = make_upload()
    document["tag_data"][0][0]["camera_intrinsics"] = [1500.0, 1500.0, 960.0]
    assert_format_error(document, "tag_data[0][0].camera_intrinsics", "4", "3")


def test_corners_wrong_length():
    document = make_upload()
    document["tag_data"][0][0]["tag_corners_pixel_coordinates"] = [1.0] * 6
    assert_format_error(document, "tag_data[0][0].tag_corners_pixel_coordinates", "8", "6")


def test_joint_covar_wrong_length():
    document = make_upload()
    document["tag_data"][0][0]["joint_covar"] = [0.0] * 36
    assert_format_error(document, "tag_data[0][0].joint_covar", "49", "36")


def test_missing_tag_pose():
    document = make_upload()
    del document["tag_data"][1][1]["tag_pose"]
    assert_format_error(document, "tag_data[1][1].tag_pose", "missing")


def test_tag_data_not_a_list():
    document = make_upload()
    document["tag_data"] = "none"
    assert_format_error(document, "tag_data", "expected a list", "string")


def test_tag_frame_not_a_list():
    document = make_upload()
    document["tag_data"][1] = 42
    assert_format_error(document, "tag_data[1]", "expected a list", "number")


def test_detection_not_an_object():
    document = make_upload()
    document["tag_data"][1][1] = [1, 2]
    assert_format_error(document, "tag_data[1][1]", "expected an object", "list")


def test_huge_pose_id_is_a_format_error():
    # JSON integers are unbounded; an id past int64 must be refused, not overflow numpy.
    document = make_upload(frames=[])
    document["pose_data"][4]["id"] = 10**30
    with pytest.raises(SessionFormatError) as info:
        parse_session(document)
    assert info.value.field == "pose_data[4].id"


def test_huge_tag_id_is_a_format_error():
    document = make_upload()
    document["tag_data"][0][0]["tag_id"] = 10**30
    with pytest.raises(SessionFormatError) as info:
        parse_session(document)
    assert info.value.field == "tag_data[0][0].tag_id"


def test_huge_rotation_entry_is_a_format_error_without_warnings():
    # 1e200 is a finite JSON number; RᵀR overflows. It is not a rotation, and numpy's overflow
    # RuntimeWarning must not escape (pytest turns warnings into errors).
    document = make_upload()
    document["pose_data"][1]["pose"][0] = 1e200
    assert_format_error(document, "pose_data[1].pose", "not orthonormal")


# --------------------------------------------------------------------------- property tests

json_scalars = (
    st.none()
    | st.booleans()
    | st.integers()
    | st.floats()  # NaN and ±Infinity included: Python's json.loads accepts them
    | st.text(max_size=8)
)
json_values = st.recursive(
    json_scalars,
    lambda children: (
        st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=8), children, max_size=4)
    ),
    max_leaves=12,
)


def accepts_or_format_error(document: Any) -> Session | None:
    try:
        return parse_session(document)
    except SessionFormatError as err:
        message = str(err)
    assert message
    assert "\n" not in message
    return None


@settings(max_examples=200, deadline=None)
@given(json_values)
def test_arbitrary_json_raises_only_format_errors(value):
    accepts_or_format_error(value)


numbers16 = st.lists(st.floats(), min_size=16, max_size=16)
session_like = st.fixed_dictionaries(
    {
        "map_id": st.text(max_size=4) | json_scalars,
        "pose_data": st.lists(
            st.fixed_dictionaries(
                {"id": st.integers() | json_scalars, "timestamp": json_scalars, "pose": numbers16}
            )
            | json_values,
            max_size=3,
        ),
        "tag_data": st.lists(st.lists(json_values, max_size=2), max_size=2) | json_values,
        "location_data": json_values,
    }
)


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(session_like)
def test_arbitrary_session_shaped_json_raises_only_format_errors(document):
    accepts_or_format_error(document)


def node_paths(node: Any, prefix: tuple[Any, ...] = ()) -> Iterator[tuple[Any, ...]]:
    """Every path to a value inside ``node`` (dict keys and list indices)."""
    if isinstance(node, dict):
        items: Any = node.items()
    elif isinstance(node, list):
        items = enumerate(node)
    else:
        return
    for key, child in items:
        yield (*prefix, key)
        yield from node_paths(child, (*prefix, key))


def small_valid_upload() -> dict[str, Any]:
    return make_upload(
        3,
        frames=[
            [make_detection(tag_id=1, pose_id=1)],
            [make_detection(tag_id=2, pose_id=2), make_detection(tag_id=1, pose_id=2)],
        ],
        locations=[make_location("lab", 2)],
    )


VALID_PATHS = list(node_paths(small_valid_upload()))


def replaced(document: Any, path: tuple[Any, ...], value: Any) -> Any:
    document = copy.deepcopy(document)
    parent = document
    for key in path[:-1]:
        parent = parent[key]
    parent[path[-1]] = value
    return document


def deleted(document: Any, path: tuple[Any, ...]) -> Any:
    document = copy.deepcopy(document)
    parent = document
    for key in path[:-1]:
        parent = parent[key]
    del parent[path[-1]]
    return document


def test_small_valid_upload_is_valid():
    session = parse_session(small_valid_upload())
    assert len(session.detections) == 3
    assert len(session.pois) == 1
    assert len(VALID_PATHS) > 100


@settings(max_examples=200, deadline=None)
@given(st.sampled_from(VALID_PATHS), json_values)
def test_replacing_any_value_raises_only_format_errors(path, value):
    accepts_or_format_error(replaced(small_valid_upload(), path, value))


@settings(max_examples=200, deadline=None)
@given(st.sampled_from(VALID_PATHS), st.floats() | st.integers())
def test_replacing_any_value_by_a_number_raises_only_format_errors(path, value):
    accepts_or_format_error(replaced(small_valid_upload(), path, value))


@settings(max_examples=100, deadline=None)
@given(st.sampled_from(VALID_PATHS))
def test_deleting_any_value_raises_only_format_errors(path):
    accepts_or_format_error(deleted(small_valid_upload(), path))


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=64))
def test_arbitrary_bytes_raise_only_format_errors(raw):
    try:
        decode_json_bytes(raw)
    except SessionFormatError as err:
        message = str(err)
    else:
        return
    assert message


@settings(max_examples=100, deadline=None)
@given(st.integers(min_value=0, max_value=400))
def test_any_cut_of_a_real_file_is_a_format_error(cut_at):
    raw = (SESSIONS_DIR / "onetag.json").read_bytes()
    with pytest.raises(SessionFormatError):
        parse_session(decode_json_bytes(raw[: len(raw) * cut_at // 401]))


def test_huge_last_row_entry_is_a_format_error_without_warnings():
    """Found by Hypothesis: 1.8e302 in a pose's last entry overflowed np.allclose."""
    document = make_upload(num_poses=3)
    document["pose_data"][0]["pose"][15] = 1.797693134862316e302
    with pytest.raises(SessionFormatError, match=r"pose_data\[0\]\.pose: last row"):
        parse_session(document)
