"""Ground-truth import: RTAB-Map exports, the JSON form, and the errors on bad input."""

from __future__ import annotations

import gzip
import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from app.domain.errors import GroundTruthFormatError
from app.domain.evaluation.ground_truth import (
    YUP_R_RTABMAP,
    ground_truth_to_json,
    load_ground_truth,
    parse_ground_truth_json,
    parse_ground_truth_text,
    parse_rtabmap_export,
)
from app.domain.frames import make_pose, rotation_angle_rad, rotation_from_quat_xyzw

GROUND_TRUTH_DIR = Path(__file__).parents[2] / "data" / "ground_truth"


# --------------------------------------------------------------------------- RTAB-Map conversion


def test_yup_r_rtabmap_sends_rtabmap_up_to_app_up():
    # RTAB-Map is z up, the app is y up: A·z = y, and A·x = -z, A·y = -x.
    np.testing.assert_allclose(YUP_R_RTABMAP @ [0, 0, 1], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(YUP_R_RTABMAP @ [1, 0, 0], [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(YUP_R_RTABMAP @ [0, 1, 0], [-1, 0, 0], atol=1e-12)


def test_single_line_converts_by_hand():
    poses = parse_rtabmap_export("rpy 5 1.0 2.0 3.0 0 0 0\n")
    assert list(poses) == [5]
    # p' = A·(1, 2, 3) = (-2, 3, -1); with zero angles R' = A·A, which is Aᵀ (A is a 120° turn).
    # fmt: off
    expected_R = np.array([[ 0.0, 0.0, -1.0],
                           [-1.0, 0.0,  0.0],
                           [ 0.0, 1.0,  0.0]])
    # fmt: on
    np.testing.assert_allclose(poses[5], make_pose(expected_R, [-2.0, 3.0, -1.0]), atol=1e-12)


def test_roll_pitch_yaw_compose_as_rx_ry_rz_before_the_frame_change():
    roll, pitch, yaw = 0.3, -0.2, 1.1
    pose = parse_rtabmap_export(f"rpy 1 0 0 0 {roll} {pitch} {yaw}")[1]
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    np.testing.assert_allclose(pose[:3, :3], Rx @ Ry @ Rz @ YUP_R_RTABMAP.T, atol=1e-12)


def test_negative_ids_blank_lines_and_comments_are_skipped():
    text = "# exported by RTAB-Map\n\nrpy -1 1 2 3 0 0 0\n   \nrpy 7 1 2 3 0 0 0\n  # end\n"
    assert list(parse_rtabmap_export(text)) == [7]


def test_rtabmap_import_reproduces_the_yup_reference():
    converted = load_ground_truth(GROUND_TRUTH_DIR / "rtabmap_mac_1_2.txt")
    reference = load_ground_truth(GROUND_TRUTH_DIR / "mac_1_2_yup_reference.json")
    assert sorted(converted) == sorted(reference)
    assert len(converted) == 52
    for tag_id, world_T_tag in converted.items():
        expected = reference[tag_id]
        np.testing.assert_allclose(world_T_tag[:3, 3], expected[:3, 3], atol=1e-6)
        angle_deg = math.degrees(rotation_angle_rad(expected[:3, :3].T @ world_T_tag[:3, :3]))
        assert angle_deg < 0.01, f"tag {tag_id}: rotation off by {angle_deg:.4f}°"


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("rpy 5 1 2 3 0 0\n", "line 1: expected 8 fields"),
        ("rpy 5 1 2 3 0 0 0\nrpy 6 1 2 3 0 0 0 9\n", "line 2: expected 8 fields"),
        ("rpy 5 1 2 3 0 0 0\nxyz 6 1 2 3 0 0 0\n", "line 2: expected 'rpy TAG_ID"),
        ("rpy five 1 2 3 0 0 0\n", "line 1: tag id 'five' is not an integer"),
        ("rpy 5.5 1 2 3 0 0 0\n", "line 1: tag id '5.5' is not an integer"),
        ("rpy 5 1 two 3 0 0 0\n", "line 1: y 'two' is not a number"),
        ("\n\nrpy 5 1 2 3 nan 0 0\n", "line 3: roll is a non-finite number nan"),
        ("rpy 5 1 2 inf 0 0 0\n", "line 1: z is a non-finite number inf"),
        ("rpy 5 1 2 3 0 0 0\nrpy 5 1 2 3 0 0 0\n", "line 2: tag 5 already given on line 1"),
        ("# nothing\nrpy -3 1 2 3 0 0 0\n", "no tag poses"),
    ],
)
def test_malformed_rtabmap_export_names_line_and_reason(text, message):
    with pytest.raises(GroundTruthFormatError, match=message):
        parse_rtabmap_export(text)


# --------------------------------------------------------------------------- JSON form


def _document(*poses):
    return {"poses": [{"tag_id": tag_id, "pose": pose} for tag_id, pose in poses]}


def test_json_pose_is_position_and_quat_xyzw():
    # Quaternion (0, sin 45°, 0, cos 45°) is +90° about y; given unnormalized, it is normalized.
    poses = parse_ground_truth_json(_document((3, [1, 2, 3, 0, 2, 0, 2])))
    # fmt: off
    expected_R = np.array([[ 0.0, 0.0, 1.0],
                           [ 0.0, 1.0, 0.0],
                           [-1.0, 0.0, 0.0]])
    # fmt: on
    np.testing.assert_allclose(poses[3], make_pose(expected_R, [1, 2, 3]), atol=1e-12)


@pytest.mark.parametrize(
    ("document", "message"),
    [
        ([], "expected a JSON object, got a list"),
        ({}, "poses: missing"),
        ({"poses": {}}, "poses: expected a list, got an object"),
        ({"poses": []}, "poses: empty"),
        ({"poses": [3]}, r"poses\[0\]: expected an object, got a number"),
        ({"poses": [{"pose": [0, 0, 0, 0, 0, 0, 1]}]}, r"poses\[0\].tag_id: missing"),
        (_document((True, [0, 0, 0, 0, 0, 0, 1])), r"poses\[0\].tag_id: expected an integer"),
        (_document((1.5, [0, 0, 0, 0, 0, 0, 1])), r"poses\[0\].tag_id: expected an integer"),
        (_document((-2, [0, 0, 0, 0, 0, 0, 1])), r"poses\[0\].tag_id: must be ≥ 0, got -2"),
        ({"poses": [{"tag_id": 1}]}, r"poses\[0\].pose: missing"),
        (_document((1, "0 0 0")), r"poses\[0\].pose: expected a list of 7 numbers"),
        (_document((1, [0, 0, 0, 1])), r"poses\[0\].pose: expected 7 numbers .*, got 4"),
        (_document((1, [0, 0, 0, 0, 0, 0, 1, 0])), r"poses\[0\].pose: expected 7 .*, got 8"),
        (_document((1, [0, 0, "0", 0, 0, 0, 1])), r"poses\[0\].pose\[2\]: expected a number"),
        (_document((1, [0, math.nan, 0, 0, 0, 0, 1])), r"poses\[0\].pose\[1\]: non-finite"),
        (_document((1, [0, 0, 0, 0, 0, 0, math.inf])), r"poses\[0\].pose\[6\]: non-finite"),
        (_document((1, [0, 0, 0, 0, 0, 0, 0])), r"poses\[0\].pose: quaternion .* is zero"),
        (
            _document(
                (4, [0, 0, 0, 0, 0, 0, 1]), (5, [0, 0, 0, 0, 0, 0, 1]), (4, [1, 0, 0, 0, 0, 0, 1])
            ),
            r"poses\[2\].tag_id: tag 4 already given at poses\[0\]",
        ),
    ],
)
def test_malformed_json_names_field_and_reason(document, message):
    with pytest.raises(GroundTruthFormatError, match=message):
        parse_ground_truth_json(document)


def test_json_extra_keys_are_ignored():
    document = {"source": "tape", "poses": [{"tag_id": 0, "pose": [0, 0, 0, 0, 0, 0, 1], "x": 1}]}
    np.testing.assert_allclose(parse_ground_truth_json(document)[0], np.eye(4))


def test_to_json_is_sorted_and_parses_back():
    poses = {
        9: make_pose(np.eye(3), [1, 2, 3]),
        2: make_pose(rotation_from_quat_xyzw([0, 1, 0, 0]), [0, 0, 0]),
    }
    document = ground_truth_to_json(poses)
    assert [entry["tag_id"] for entry in document["poses"]] == [2, 9]
    assert document["poses"][1]["pose"] == [1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 1.0]
    parsed = parse_ground_truth_json(json.loads(json.dumps(document)))
    for tag_id, pose in poses.items():
        np.testing.assert_allclose(parsed[tag_id], pose, atol=1e-12)


unit_quaternions = st.tuples(*[st.floats(-1, 1) for _ in range(4)]).filter(
    lambda q: np.linalg.norm(q) > 0.1
)
positions = st.tuples(*[st.floats(-100, 100) for _ in range(3)])


@given(st.dictionaries(st.integers(0, 1000), st.tuples(unit_quaternions, positions), min_size=1))
def test_json_round_trip(raw):
    poses = {
        tag_id: make_pose(rotation_from_quat_xyzw(quat_xyzw), xyz)
        for tag_id, (quat_xyzw, xyz) in raw.items()
    }
    parsed = parse_ground_truth_json(json.loads(json.dumps(ground_truth_to_json(poses))))
    assert parsed.keys() == poses.keys()
    for tag_id, pose in poses.items():
        np.testing.assert_allclose(parsed[tag_id], pose, atol=1e-9)


# --------------------------------------------------------------------------- files


def test_load_detects_json_form(tmp_path):
    path = tmp_path / "gt.json"
    path.write_text(json.dumps(_document((1, [1, 2, 3, 0, 0, 0, 1]))))
    np.testing.assert_allclose(load_ground_truth(path)[1][:3, 3], [1, 2, 3])


def test_load_reads_the_tape_measured_json():
    poses = load_ground_truth(GROUND_TRUTH_DIR / "occam_room_tape.json")
    assert sorted(poses) == list(range(8))


def test_load_reads_gzip(tmp_path):
    path = tmp_path / "gt.txt.gz"
    path.write_bytes(gzip.compress(b"rpy 1 0 0 0 0 0 0\n"))
    assert list(load_ground_truth(path)) == [1]


def test_text_with_leading_comment_is_rtabmap():
    assert list(parse_ground_truth_text("# RTAB-Map\nrpy 2 0 0 0 0 0 0\n")) == [2]


def test_missing_file_names_the_file(tmp_path):
    path = tmp_path / "nowhere.txt"
    with pytest.raises(GroundTruthFormatError, match=r"cannot read .*nowhere\.txt"):
        load_ground_truth(path)


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"tag,x,y,z\n1,0,0,0\n", "unknown ground-truth form: expected a JSON object"),
        (b"", "empty: no tag poses"),
        (b'{"poses": [', "not valid JSON"),
        (b"\xff\xfe\x00", "not UTF-8 text"),
        (b"rpy 1 0 0 0 0 0 0\nrpy 2 0 0\n", "line 2: expected 8 fields"),
        (b'{"poses": [{"tag_id": 1, "pose": [0, 0, 0, 0, 0, 0, NaN]}]}', r"pose\[6\]: non-finite"),
    ],
)
def test_bad_file_error_names_file_and_problem(tmp_path, content, message):
    path = tmp_path / "bad_gt.txt"
    path.write_bytes(content)
    with pytest.raises(GroundTruthFormatError, match=message) as caught:
        load_ground_truth(path)
    assert str(caught.value).startswith(f"{path}: ")
