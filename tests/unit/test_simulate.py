"""Simulated sessions: the upload format, the frame conventions, and the truth behind them.

The noiseless frame-convention test here is THE check of the app's conventions (§2) across
the project: column-major ``pose``, row-major OpenCV ``tag_pose`` and the diag(1, −1, −1, 1) flip.
"""

from __future__ import annotations

import dataclasses
import json
import math
from typing import Any

import numpy as np
import pytest

from app.domain.errors import ParameterError
from app.domain.evaluation.ground_truth import parse_ground_truth_json
from app.domain.evaluation.simulate import (
    SimulatedSession,
    SimulationConfig,
    simulate_session,
)
from app.domain.frames import PHONE_T_CAMERA_CV, FloatArray, relative_se3, rotation_angle_rad
from app.domain.upload.session import parse_session

TAG_SIZE_M = 0.173


def tag_corners_px(camera_T_tag: FloatArray, intrinsics: FloatArray) -> FloatArray:
    """(M, 4, 2) the architecture §2 corner pixels, written out independently of the simulator."""
    h = TAG_SIZE_M / 2
    corners_tag = np.array([[-h, -h, 0, 1], [h, -h, 0, 1], [h, h, 0, 1], [-h, h, 0, 1]]).T
    points = camera_T_tag @ corners_tag  # (M, 4, 4): rows x, y, z, 1 per corner column
    fx, fy, cx, cy = (intrinsics[:, k, None] for k in range(4))
    u = fx * points[:, 0] / points[:, 2] + cx
    v = fy * points[:, 1] / points[:, 2] + cy
    return np.stack([u, v], axis=-1)


@pytest.fixture(scope="module")
def noisy() -> SimulatedSession:
    return simulate_session(SimulationConfig(num_poses=3000, seed=1))


@pytest.fixture(scope="module")
def noiseless() -> SimulatedSession:
    return simulate_session(SimulationConfig(num_poses=3000, seed=1).without_noise())


@pytest.fixture(scope="module")
def ten_k() -> SimulatedSession:
    return simulate_session(SimulationConfig(num_poses=10_000, seed=2))


@pytest.fixture(scope="module")
def two_floors() -> SimulatedSession:
    return simulate_session(SimulationConfig(num_poses=3000, two_floors=True, seed=3))


@pytest.fixture(scope="module")
def with_outliers() -> SimulatedSession:
    return simulate_session(SimulationConfig(num_poses=10_000, outlier_fraction=0.1, seed=4))


# --------------------------------------------------------------------------- the upload format


def test_parse_session_accepts_the_upload_and_its_json(noisy: SimulatedSession) -> None:
    text = json.dumps(noisy.upload)
    session = parse_session(json.loads(text))

    assert session.map_id == "simulated"
    assert session.num_poses == 3000
    assert session.warnings == ()
    np.testing.assert_array_equal(session.pose_id, np.arange(3000))
    np.testing.assert_allclose(np.diff(session.timestamp_s), 0.1, atol=1e-9)
    assert len(session.detections) == noisy.detection_tag_id.shape[0] > 0
    np.testing.assert_array_equal(session.detections.tag_id, noisy.detection_tag_id)
    np.testing.assert_array_equal(session.detections.pose_index, noisy.detection_pose_index)
    np.testing.assert_allclose(session.world_T_phone, noisy.world_T_phone_odometry, atol=1e-12)
    assert len(session.pois) == 2
    assert noisy.upload["plane_data"] == []
    assert all(pose["planes"] == [] for pose in noisy.upload["pose_data"])


def test_every_detection_carries_the_app_fields(noisy: SimulatedSession) -> None:
    lengths = {
        "tag_pose": 16,
        "camera_intrinsics": 4,
        "tag_corners_pixel_coordinates": 8,
        "tag_position_variance": 3,
        "tag_orientation_variance": 4,
        "joint_covar": 49,
    }
    for frame in noisy.upload["tag_data"]:
        assert isinstance(frame, list)
        assert len({d["pose_id"] for d in frame}) == 1
        for detection in frame:
            assert {"tag_id", "pose_id", "timestamp", *lengths} <= detection.keys()
            for key, length in lengths.items():
                assert len(detection[key]) == length, key
            assert (
                detection["timestamp"]
                == noisy.upload["pose_data"][detection["pose_id"]]["timestamp"]
            )
            assert detection["camera_intrinsics"] == [1460.0, 1460.0, 925.0, 725.0]


def test_joint_covariance_is_a_plausible_covariance(noisy: SimulatedSession) -> None:
    detections = parse_session(noisy.upload).detections
    covariance = detections.joint_covariance
    np.testing.assert_allclose(covariance, np.swapaxes(covariance, 1, 2), atol=1e-15)
    assert np.linalg.eigvalsh(covariance).min() > -1e-12
    np.testing.assert_allclose(
        detections.position_variance_m2, np.diagonal(covariance, axis1=1, axis2=2)[:, :3]
    )
    # From pixel noise, the depth (z, OpenCV) is the weak axis, and far tags are less certain.
    assert np.median(detections.position_variance_m2[:, 2]) > 5 * np.median(
        detections.position_variance_m2[:, 0]
    )
    distance_m = np.linalg.norm(detections.camera_T_tag[:, :3, 3], axis=1)
    near, far = distance_m < np.median(distance_m), distance_m >= np.median(distance_m)
    depth_var = detections.position_variance_m2[:, 2]
    assert np.median(depth_var[far]) > np.median(depth_var[near])


# --------------------------------------------------------------------------- frame conventions


@pytest.mark.parametrize(
    ("phone_roll_deg", "two_floors"), [(0.0, False), (90.0, False), (180.0, True)]
)
def test_noiseless_observed_tag_poses_equal_the_truth(
    phone_roll_deg: float, two_floors: bool
) -> None:
    """Column-major poses, row-major OpenCV tag poses and the diag(1, −1, −1, 1) flip all agree."""
    config = SimulationConfig(
        num_poses=2500, phone_roll_deg=phone_roll_deg, two_floors=two_floors, seed=5
    ).without_noise()
    sim = simulate_session(config)
    session = parse_session(json.loads(json.dumps(sim.upload)))

    observed = session.world_T_tag_observed()
    truth = np.stack([sim.world_T_tag_true[int(t)] for t in session.detections.tag_id])
    assert observed.shape[0] > 50
    np.testing.assert_allclose(observed, truth, atol=1e-9)
    np.testing.assert_allclose(session.world_T_phone, sim.world_T_phone_true, atol=1e-12)


def test_raw_encoding_follows_design_section_2(noiseless: SimulatedSession) -> None:
    """Read the raw lists by hand: translation at 12–14 of ``pose``, at 3, 7, 11 of ``tag_pose``."""
    first = noiseless.upload["pose_data"][0]["pose"]
    np.testing.assert_allclose(first[12:15], noiseless.world_T_phone_true[0, :3, 3], atol=1e-12)
    assert first[3] == first[7] == first[11] == 0.0
    assert first[15] == 1.0

    detection = noiseless.upload["tag_data"][0][0]
    tag_pose = detection["tag_pose"]
    world_T_phone = noiseless.world_T_phone_true[detection["pose_id"]]
    world_T_tag = noiseless.world_T_tag_true[detection["tag_id"]]
    p_phone = np.linalg.solve(world_T_phone, world_T_tag[:, 3])[:3]  # tag centre, phone frame
    # OpenCV: x right (same), y down and z forward (both flipped from ARKit's y up, −z forward).
    np.testing.assert_allclose(
        [tag_pose[3], tag_pose[7], tag_pose[11]], [p_phone[0], -p_phone[1], -p_phone[2]], atol=1e-9
    )
    assert tag_pose[11] > 0  # in front of the camera
    assert tag_pose[12:] == [0.0, 0.0, 0.0, 1.0]


def test_corners_from_the_true_pose_are_inside_the_image(
    noiseless: SimulatedSession, noisy: SimulatedSession
) -> None:
    for sim in (noiseless, noisy):
        intrinsics = np.tile([1460.0, 1460.0, 925.0, 725.0], (sim.camera_T_tag_true.shape[0], 1))
        corners = tag_corners_px(sim.camera_T_tag_true, intrinsics)
        assert np.all(corners[..., 0] >= 0)
        assert np.all(corners[..., 0] <= 1850)
        assert np.all(corners[..., 1] >= 0)
        assert np.all(corners[..., 1] <= 1450)
    # Without noise, the reported corners are exactly the projection of the true pose.
    detections = parse_session(noiseless.upload).detections
    np.testing.assert_allclose(
        detections.corners_px,
        tag_corners_px(noiseless.camera_T_tag_true, detections.intrinsics),
        atol=1e-9,
    )


def test_tags_face_the_camera_within_the_view_angle_and_distance(noisy: SimulatedSession) -> None:
    tag_xyz = np.stack([noisy.world_T_tag_true[int(t)][:3, 3] for t in noisy.detection_tag_id])
    tag_z = np.stack([noisy.world_T_tag_true[int(t)][:3, 2] for t in noisy.detection_tag_id])
    to_camera = noisy.world_T_phone_true[noisy.detection_pose_index, :3, 3] - tag_xyz
    distance_m = np.linalg.norm(to_camera, axis=1)
    cos_view = np.einsum("ni,ni->n", tag_z, to_camera) / distance_m

    assert np.all(cos_view > 0)  # +z points out of the wall, toward the viewer
    assert np.all(cos_view >= math.cos(math.radians(60.0)) - 1e-12)
    assert np.all(distance_m <= 3.0 + 1e-12)
    # The same fact seen from the camera: the tag's +z points back at it (−z, OpenCV).
    assert np.all(noisy.camera_T_tag_true[:, 2, 2] < 0)


# --------------------------------------------------------------------------- building and walk


def test_tags_hang_upright_on_the_walls_every_4_to_10_m(noisy: SimulatedSession) -> None:
    building = noisy.building
    for world_T_tag in building.world_T_tag.values():
        np.testing.assert_allclose(world_T_tag[:3, 1], [0.0, 1.0, 0.0], atol=1e-12)  # +y up
        assert abs(world_T_tag[1, 2]) < 1e-12  # +z horizontal, out of the wall
        assert 1.2 <= world_T_tag[1, 3] <= 1.6
        np.testing.assert_allclose(
            world_T_tag[:3, :3].T @ world_T_tag[:3, :3], np.eye(3), atol=1e-12
        )
    for tag_ids in building.corridor_tag_ids:
        assert len(tag_ids) >= 2
        offsets = np.array([building.tag_offset_along_m[t] for t in tag_ids])
        gaps = np.diff(offsets)
        assert np.all(gaps >= 4.0 - 1e-9)
        assert np.all(gaps <= 10.0 + 1e-9)
    ids = sorted(building.world_T_tag)
    assert ids == list(range(len(ids)))


def test_the_camera_stays_inside_the_building(two_floors: SimulatedSession) -> None:
    xyz = two_floors.world_T_phone_true[:, :3, 3]
    boxes = two_floors.building.free_space_boxes_m
    inside = np.all(
        (xyz[:, None] >= boxes[None, :, 0]) & (xyz[:, None] <= boxes[None, :, 1]), axis=2
    )
    assert np.all(np.any(inside, axis=1))


def test_the_walk_is_at_walking_speed_with_an_upright_phone(noisy: SimulatedSession) -> None:
    step_m = np.linalg.norm(np.diff(noisy.world_T_phone_true[:, :3, 3], axis=0), axis=1)
    assert np.median(step_m) == pytest.approx(0.12, rel=0.15)  # 1.2 m/s at 10 Hz
    assert step_m.max() < 0.3
    up_in_phone = noisy.world_T_phone_true[:, 1, :3]  # world y in phone coordinates
    assert np.all(up_in_phone[:, 1] > math.cos(math.radians(20)))  # ARKit y up, give or take
    np.testing.assert_allclose(noisy.world_T_phone_true[:, 1, 3], 1.3, atol=0.1)


def test_10k_poses_have_a_sensible_number_of_detections(ten_k: SimulatedSession) -> None:
    count = ten_k.detection_tag_id.shape[0]
    assert 300 <= count <= 3000  # real sessions: tens to hundreds per 1000 poses
    assert ten_k.detected_tag_ids == sorted(ten_k.world_T_tag_true)  # the whole building
    # Loop closures: most tags are seen on several passes, minutes apart.
    revisited = 0
    for tag_id in ten_k.detected_tag_ids:
        times_s = ten_k.detection_pose_index[ten_k.detection_tag_id == tag_id] / 10.0
        revisited += int(np.any(np.diff(times_s) > 30.0))
    assert revisited >= 0.8 * len(ten_k.detected_tag_ids)


def test_two_floors_span_two_heights_3_5_m_apart(two_floors: SimulatedSession) -> None:
    height_m = two_floors.world_T_phone_true[:, 1, 3]
    lower, upper = height_m < 3.0, height_m > 4.5
    assert lower.mean() > 0.2
    assert upper.mean() > 0.2
    assert np.median(height_m[upper]) - np.median(height_m[lower]) == pytest.approx(3.5, abs=0.05)
    assert two_floors.building.floor_heights_m == (0.0, 3.5)
    seen_height_m = np.array(
        [two_floors.world_T_tag_true[int(t)][1, 3] for t in two_floors.detection_tag_id]
    )
    assert np.any(seen_height_m < 2.0)
    assert np.any(seen_height_m > 4.5)


# --------------------------------------------------------------------------- noise


def test_odometry_starts_on_the_truth_and_drifts_about_1_percent() -> None:
    # A straight 120 m corridor, where drift is not bounded by walking in loops.
    errors = []
    for seed in range(8):
        config = SimulationConfig(
            num_poses=1000, blocks=(1, 1), block_size_m=(200.0, 20.0), seed=seed
        )
        sim = simulate_session(config)
        np.testing.assert_allclose(
            sim.world_T_phone_odometry[0], sim.world_T_phone_true[0], atol=1e-12
        )
        errors.append(sim.odometry_end_error_m() / sim.path_length_m())
    assert 0.002 < float(np.mean(errors)) < 0.03


def test_odometry_is_locally_right_and_keeps_gravity(noisy: SimulatedSession) -> None:
    odometry, truth = noisy.world_T_phone_odometry, noisy.world_T_phone_true
    step_odometry = relative_se3(odometry[:-1], odometry[1:])
    step_truth = relative_se3(truth[:-1], truth[1:])
    step_error_m = np.linalg.norm(step_odometry[:, :3, 3] - step_truth[:, :3, 3], axis=1)
    assert np.max(step_error_m) < 0.05
    # Heading drifts; roll and pitch do not (ARKit observes gravity): the up vector seen by the
    # phone stays within about half a degree of the truth all along.
    up_odometry, up_truth = odometry[:, 1, :3], truth[:, 1, :3]
    tilt_error_rad = np.arccos(np.clip(np.einsum("ni,ni->n", up_odometry, up_truth), -1, 1))
    assert np.max(tilt_error_rad) < 0.01
    assert rotation_angle_rad(odometry[-1, :3, :3] @ truth[-1, :3, :3].T) > 0.0


def test_tag_noise_is_larger_along_the_line_of_sight(ten_k: SimulatedSession) -> None:
    detections = parse_session(ten_k.upload).detections
    error = detections.camera_T_tag[:, :3, 3] - ten_k.camera_T_tag_true[:, :3, 3]
    distance_m = np.linalg.norm(ten_k.camera_T_tag_true[:, :3, 3], axis=1)
    line_of_sight = ten_k.camera_T_tag_true[:, :3, 3] / distance_m[:, None]
    along = np.einsum("ni,ni->n", error, line_of_sight)
    across = np.linalg.norm(error - along[:, None] * line_of_sight, axis=1) / math.sqrt(2)
    # σ = 0.01 m × distance across, × 3 along.
    assert np.std(along / distance_m) == pytest.approx(0.03, rel=0.15)
    assert np.sqrt(np.mean((across / distance_m) ** 2)) == pytest.approx(0.01, rel=0.15)
    # Inlier corners agree with the reported pose (the app's pose comes from them) to ~1 px.
    reprojection_px = np.linalg.norm(
        detections.corners_px - tag_corners_px(detections.camera_T_tag, detections.intrinsics),
        axis=2,
    )
    assert np.median(reprojection_px) < 1.0
    assert np.max(reprojection_px) < 4.0


def test_outliers_are_grossly_wrong_and_betrayed_by_their_corners(
    with_outliers: SimulatedSession,
) -> None:
    outlier = with_outliers.detection_is_outlier
    assert outlier.mean() == pytest.approx(0.1, abs=0.03)
    detections = parse_session(with_outliers.upload).detections
    position_error_m = np.linalg.norm(
        detections.camera_T_tag[:, :3, 3] - with_outliers.camera_T_tag_true[:, :3, 3], axis=1
    )
    assert np.all(position_error_m[outlier] > 0.1)
    assert np.median(position_error_m[~outlier]) < 0.05
    reprojection_px = np.linalg.norm(
        detections.corners_px - tag_corners_px(detections.camera_T_tag, detections.intrinsics),
        axis=2,
    ).mean(axis=1)
    assert reprojection_px[outlier].min() > 4.0
    assert reprojection_px[~outlier].max() < 4.0


def test_noise_changes_neither_the_truth_nor_which_detections_happen(
    noisy: SimulatedSession, noiseless: SimulatedSession
) -> None:
    np.testing.assert_array_equal(noisy.world_T_phone_true, noiseless.world_T_phone_true)
    np.testing.assert_array_equal(noisy.detection_pose_index, noiseless.detection_pose_index)
    np.testing.assert_array_equal(noisy.detection_tag_id, noiseless.detection_tag_id)
    assert not np.array_equal(noisy.world_T_phone_odometry, noiseless.world_T_phone_odometry)
    np.testing.assert_array_equal(noiseless.world_T_phone_odometry, noiseless.world_T_phone_true)


# --------------------------------------------------------------------------- the rest


def test_same_seed_same_session_other_seed_other_session() -> None:
    config = SimulationConfig(num_poses=1500, outlier_fraction=0.05, seed=7)
    first, second = simulate_session(config), simulate_session(config)
    assert json.dumps(first.upload) == json.dumps(second.upload)
    np.testing.assert_array_equal(first.world_T_phone_true, second.world_T_phone_true)
    other = simulate_session(dataclasses.replace(config, seed=8))
    assert json.dumps(other.upload) != json.dumps(first.upload)


def test_poi_pose_id_is_one_too_high_as_the_app_writes_it(noisy: SimulatedSession) -> None:
    session = parse_session(noisy.upload)  # corrects the app's off-by-one by default
    assert [poi.name for poi in session.pois] == list(noisy.world_T_poi_true)
    for entry, poi in zip(noisy.upload["location_data"], session.pois, strict=True):
        assert poi.pose_index == entry["pose_id"] - 1
        world_T_poi = noisy.world_T_phone_true[poi.pose_index] @ poi.phone_T_poi
        np.testing.assert_allclose(world_T_poi, noisy.world_T_poi_true[poi.name], atol=1e-12)
        # The pose the app names is the *next* one: it misplaces the POI by a walking step.
        wrong = noisy.world_T_phone_true[entry["pose_id"]] @ poi.phone_T_poi
        assert np.linalg.norm(wrong[:3, 3] - world_T_poi[:3, 3]) > 0.05
    uncorrected = parse_session(noisy.upload, correct_poi_pose_id=False)
    assert [p.pose_index for p in uncorrected.pois] == [p.pose_index + 1 for p in session.pois]


def test_ground_truth_json_round_trips(noisy: SimulatedSession) -> None:
    document = json.loads(json.dumps(noisy.ground_truth_json()))
    poses = parse_ground_truth_json(document)
    assert sorted(poses) == sorted(noisy.world_T_tag_true)
    for tag_id, world_T_tag in poses.items():
        np.testing.assert_allclose(world_T_tag, noisy.world_T_tag_true[tag_id], atol=1e-12)
    detected = parse_ground_truth_json(noisy.ground_truth_json(detected_only=True))
    assert sorted(detected) == noisy.detected_tag_ids
    assert all(len(entry["pose"]) == 7 for entry in document["poses"])


@pytest.mark.parametrize(
    "changes",
    [
        {"num_poses": 1},
        {"rate_hz": 0.0},
        {"detection_rate_hz": 20.0},
        {"max_view_angle_deg": 90.0},
        {"tag_spacing_m": (10.0, 4.0)},
        {"block_size_m": (2.0, 20.0)},
        {"odom_rotation_drift_rad_per_sqrt_s": -1.0},
        {"tag_position_noise_m_at_1m": math.nan},
        {"tag_depth_noise_ratio": 0.5},
        {"outlier_fraction": 1.5},
        {"two_floors": True, "floor_height_m": 2.0},
        {"map_id": " "},
    ],
)
def test_bad_configs_are_refused_naming_the_field(changes: dict[str, Any]) -> None:
    with pytest.raises(ParameterError, match=next(iter(reversed(changes)))):
        SimulationConfig(**{"num_poses": 100, **changes})


def test_str_summarizes_the_session(noisy: SimulatedSession) -> None:
    text = str(noisy)
    assert text.startswith("simulated: 3000 poses")
    assert "detections" in text
    assert "drift" in text


def test_phone_and_camera_frames_differ_by_the_cv_flip(noiseless: SimulatedSession) -> None:
    session = parse_session(noiseless.upload)
    np.testing.assert_allclose(
        session.detections.phone_T_tag, PHONE_T_CAMERA_CV @ noiseless.camera_T_tag_true, atol=1e-12
    )
