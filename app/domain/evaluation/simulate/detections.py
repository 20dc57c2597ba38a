"""Detections: which tags the camera sees from which poses (``visible_pairs``), grouped into
approaches, and their measurements with noise, bias and outliers (``measure_detections``)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from app.domain.frames import (
    PHONE_T_CAMERA_CV,
    FloatArray,
    project_pinhole_px,
    quat_xyzw_from_rotations,
    se3_inverse,
    skew,
    so3_exp,
    tag_corners_in_camera,
    tag_corners_in_tag_frame,
)

from .building import Building
from .config import (
    JOINT_COVAR_PIXEL_SIGMA,
    LINE_OF_SIGHT_SAMPLES,
    MIN_OUTLIER_DEPTH_M,
    OUTLIER_OFFSET_M,
    OUTLIER_ROTATION_RAD,
    PAIR_CHUNK,
    BoolArray,
    IntArray,
    SimulationConfig,
)
from .odometry import stretch_rng

# --------------------------------------------------------------------------- detections


def visible_pairs(
    config: SimulationConfig,
    building: Building,
    world_T_phone: FloatArray,
    world_T_tags: FloatArray,
) -> tuple[IntArray, IntArray]:
    """(pose index, tag row) of every detection, sorted by pose then tag: the tag is close enough,
    faces the camera within the view angle, projects all 4 corners inside the image, and no wall
    stands in between."""
    stride = max(1, round(config.rate_hz / config.detection_rate_hz))
    attempts = np.arange(0, world_T_phone.shape[0], stride)
    camera_xyz = world_T_phone[attempts, :3, 3]
    tag_xyz = world_T_tags[:, :3, 3]
    pose_parts, tag_parts = [], []
    for start in range(0, attempts.shape[0], PAIR_CHUNK):
        chunk = camera_xyz[start : start + PAIR_CHUNK]
        distance_m = np.linalg.norm(tag_xyz[None, :, :] - chunk[:, None, :], axis=2)
        a, t = np.nonzero(distance_m <= config.max_detection_distance_m)
        pose_parts.append(attempts[start + a])
        tag_parts.append(t)
    pose_index = np.concatenate(pose_parts).astype(np.int64)
    tag_row = np.concatenate(tag_parts).astype(np.int64)

    # View angle between the tag's +z and the line tag → camera.
    to_camera = world_T_phone[pose_index, :3, 3] - tag_xyz[tag_row]
    cos_view = np.einsum("ni,ni->n", world_T_tags[tag_row, :3, 2], to_camera)
    cos_view /= np.linalg.norm(to_camera, axis=1)
    keep = cos_view >= math.cos(math.radians(config.max_view_angle_deg))
    pose_index, tag_row = pose_index[keep], tag_row[keep]

    # All four corners in front of the camera and inside the image.
    camera_T_tag = (
        PHONE_T_CAMERA_CV @ se3_inverse(world_T_phone[pose_index]) @ world_T_tags[tag_row]
    )
    corners_camera = tag_corners_in_camera(camera_T_tag, config.tag_size_m)
    in_front = np.all(corners_camera[:, :, 2] > 1e-3, axis=1)
    pose_index, tag_row = pose_index[in_front], tag_row[in_front]
    corners_px = project_pinhole_px(corners_camera[in_front], config.camera_intrinsics)
    width, height = config.image_size_px
    inside = np.all(
        (corners_px[:, :, 0] >= 0)
        & (corners_px[:, :, 0] <= width)
        & (corners_px[:, :, 1] >= 0)
        & (corners_px[:, :, 1] <= height),
        axis=1,
    )
    pose_index, tag_row = pose_index[inside], tag_row[inside]

    # No wall in the way: the segment camera → (just off the tag) stays in the free space.
    seen_from = world_T_phone[pose_index, :3, 3]
    target = tag_xyz[tag_row] + 0.02 * world_T_tags[tag_row, :3, 2]
    fractions = np.linspace(0.0, 1.0, LINE_OF_SIGHT_SAMPLES)
    points = seen_from[:, None, :] + fractions[None, :, None] * (target - seen_from)[:, None, :]
    boxes = building.free_space_boxes_m
    in_box = np.all(
        (points[:, :, None, :] >= boxes[None, None, :, 0, :])
        & (points[:, :, None, :] <= boxes[None, None, :, 1, :]),
        axis=3,
    )
    clear = np.all(np.any(in_box, axis=2), axis=1)
    pose_index, tag_row = pose_index[clear], tag_row[clear]

    order = np.lexsort((tag_row, pose_index))
    return pose_index[order], tag_row[order]


@dataclass(frozen=True, slots=True, kw_only=True)
class Measurements:
    """What the app reports for M detections (OpenCV camera frame)."""

    camera_T_tag: FloatArray  # (M, 4, 4)
    corners_px: FloatArray  # (M, 4, 2)
    joint_covariance: FloatArray  # (M, 7, 7)
    is_outlier: BoolArray  # (M,)


def approach_ids(pose_index: IntArray, tag_row: IntArray, gap_poses: int) -> IntArray:
    """(M,) the approach of each detection: detections of one tag at most ``gap_poses`` poses
    apart are one approach; numbered in order of their first detection (detections sorted by
    pose)."""
    m = pose_index.shape[0]
    approach = np.zeros(m, dtype=np.int64)
    last: dict[int, tuple[int, int]] = {}  # tag row → (last pose, approach)
    count = 0
    for k in range(m):
        tag, pose = int(tag_row[k]), int(pose_index[k])
        seen = last.get(tag)
        if seen is None or pose - seen[0] > gap_poses:
            seen = (pose, count)
            count += 1
        approach[k] = seen[1]
        last[tag] = (pose, seen[1])
    return approach


def first_of_each(group: IntArray, count: int) -> BoolArray:
    """(M,) True for the first ``count`` rows of each group (rows in order)."""
    seen: dict[int, int] = {}
    keep = np.zeros(group.shape[0], dtype=np.bool_)
    for k, g in enumerate(group.tolist()):
        seen[g] = seen.get(g, 0) + 1
        keep[k] = seen[g] <= count
    return keep


def _approach_bias(
    config: SimulationConfig, approach: IntArray, distance_m: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """(M, 3) rotation vectors, rad, and (M, 3) position errors, m (camera frame): one draw per
    approach, shared by all its sightings (the position error × each sighting's distance). The
    real figures: :data:`REGION_ERROR_SOURCES` ("approach bias")."""
    rng = stretch_rng(config, 2)
    count = int(approach.max()) + 1 if approach.size else 0
    rotation = rng.standard_normal((count, 3)) * config.approach_bias_rotation_rad
    position = rng.standard_normal((count, 3)) * config.approach_bias_position_m_at_1m
    return rotation[approach], position[approach] * distance_m[:, None]


def measure_detections(
    config: SimulationConfig,
    camera_T_tag_true: FloatArray,
    rng: np.random.Generator,
    rng_outliers: np.random.Generator,
    *,
    approach: IntArray | None = None,
) -> Measurements:
    """Noisy ``tag_pose``, corners and covariances for the true detections.

    Inliers: position σ = noise·d across the line of sight, × ``tag_depth_noise_ratio`` along it;
    rotation σ = noise / cos(view angle) per axis; the corners are projected from the *measured*
    pose (the app's pose comes out of PnP on its corners, so the two agree to about a pixel) plus
    pixel noise. Outliers: the pose is off by 0.5–π rad and 0.3–1.5 m while the corners still show
    the true tag, so the reprojection error gives them away.
    """
    m = int(camera_T_tag_true.shape[0])
    t_true = camera_T_tag_true[:, :3, 3]
    distance_m = np.linalg.norm(t_true, axis=1)
    line_of_sight = t_true / np.maximum(distance_m, 1e-12)[:, None]
    # The tag's +z in the camera frame against the direction tag → camera (−line_of_sight).
    cos_view = np.clip(-np.einsum("ni,ni->n", camera_T_tag_true[:, :3, 2], line_of_sight), 0.1, 1)

    position_draw = rng.standard_normal((m, 3))
    along = np.einsum("ni,ni->n", position_draw, line_of_sight)[:, None] * line_of_sight
    position_noise = (position_draw - along + config.tag_depth_noise_ratio * along) * (
        config.tag_position_noise_m_at_1m * distance_m[:, None]
    )
    rotation_noise = (
        rng.standard_normal((m, 3)) * (config.tag_rotation_noise_rad / cos_view)[:, None]
    )
    corner_noise = rng.standard_normal((m, 4, 2)) * config.corner_noise_px

    biased = approach is not None and bool(
        config.approach_bias_rotation_rad or config.approach_bias_position_m_at_1m
    )
    if biased and approach is not None:
        rotation_bias, position_bias = _approach_bias(config, approach, distance_m)
        rotation_noise = rotation_noise + rotation_bias
        position_noise = position_noise + position_bias

    camera_T_tag = camera_T_tag_true.copy()
    camera_T_tag[:, :3, :3] = so3_exp(rotation_noise) @ camera_T_tag_true[:, :3, :3]
    camera_T_tag[:, :3, 3] = t_true + position_noise

    is_outlier = rng_outliers.random(size=m) < config.outlier_fraction
    axis = rng_outliers.standard_normal((m, 3))
    axis /= np.maximum(np.linalg.norm(axis, axis=1), 1e-12)[:, None]
    angle_rad = rng_outliers.uniform(OUTLIER_ROTATION_RAD[0], OUTLIER_ROTATION_RAD[1], size=m)
    direction = rng_outliers.standard_normal((m, 3))
    direction /= np.maximum(np.linalg.norm(direction, axis=1), 1e-12)[:, None]
    offset_m = rng_outliers.uniform(OUTLIER_OFFSET_M[0], OUTLIER_OFFSET_M[1], size=m)
    if np.any(is_outlier):
        bad = np.flatnonzero(is_outlier)
        camera_T_tag[bad, :3, :3] = (
            so3_exp(axis[bad] * angle_rad[bad, None]) @ camera_T_tag_true[bad, :3, :3]
        )
        moved = t_true[bad] + direction[bad] * offset_m[bad, None]
        moved[:, 2] = np.maximum(moved[:, 2], MIN_OUTLIER_DEPTH_M)
        camera_T_tag[bad, :3, 3] = moved

    corners_from = np.where(is_outlier[:, None, None], camera_T_tag_true, camera_T_tag)
    corners_px = project_pinhole_px(
        tag_corners_in_camera(corners_from, config.tag_size_m), config.camera_intrinsics
    )
    return Measurements(
        camera_T_tag=camera_T_tag,
        corners_px=corners_px + corner_noise,
        joint_covariance=_joint_covariance(camera_T_tag, config),
        is_outlier=is_outlier,
    )


def _joint_covariance(camera_T_tag: FloatArray, config: SimulationConfig) -> FloatArray:
    """(M, 7, 7) covariance of (tx, ty, tz, qx, qy, qz, qw) from 1-px corner noise.

    Gauss–Newton: Σ₆ = σ²(JᵀJ)⁻¹ over the 8 corner coordinates, J with respect to a translation
    and a camera-frame rotation (R ← exp(δθ)·R), then mapped to the quaternion by dq/dδθ.
    """
    m = camera_T_tag.shape[0]
    fx, fy, _, _ = config.camera_intrinsics
    R = camera_T_tag[:, :3, :3]
    rotated = np.einsum("nij,kj->nki", R, tag_corners_in_tag_frame(config.tag_size_m))  # (M, 4, 3)
    points = rotated + camera_T_tag[:, None, :3, 3]
    X, Y, Z = points[..., 0], points[..., 1], points[..., 2]
    d_uv_d_point = np.zeros((m, 4, 2, 3))
    d_uv_d_point[:, :, 0, 0] = fx / Z
    d_uv_d_point[:, :, 0, 2] = -fx * X / Z**2
    d_uv_d_point[:, :, 1, 1] = fy / Z
    d_uv_d_point[:, :, 1, 2] = -fy * Y / Z**2
    d_point_d_params = np.zeros((m, 4, 3, 6))
    d_point_d_params[:, :, :, :3] = np.eye(3)
    d_point_d_params[:, :, :, 3:] = -skew(rotated)
    J = (d_uv_d_point @ d_point_d_params).reshape(m, 8, 6)
    information = np.einsum("nki,nkj->nij", J, J) / JOINT_COVAR_PIXEL_SIGMA**2
    covariance_6 = np.linalg.inv(information + 1e-12 * np.eye(6))

    quat_xyzw = quat_xyzw_from_rotations(R)
    G = np.zeros((m, 7, 6))
    G[:, :3, :3] = np.eye(3)
    G[:, 3:6, 3:] = 0.5 * (quat_xyzw[:, 3, None, None] * np.eye(3) - skew(quat_xyzw[:, :3]))
    G[:, 6, 3:] = -0.5 * quat_xyzw[:, :3]
    covariance_7 = G @ covariance_6 @ np.swapaxes(G, 1, 2)
    return np.asarray(0.5 * (covariance_7 + np.swapaxes(covariance_7, 1, 2)), dtype=np.float64)
