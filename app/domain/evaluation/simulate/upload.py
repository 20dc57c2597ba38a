"""The upload document the app would send (``upload_document``), and the points of interest
written to it (``points_of_interest_of``)."""

from __future__ import annotations

from typing import Any

import numpy as np

from app.domain.frames import FloatArray

from .config import POI_NAMES, POI_OFFSET_PHONE_M, START_TIME_S, IntArray, SimulationConfig
from .detections import Measurements

# --------------------------------------------------------------------------- points of interest


def points_of_interest_of(
    config: SimulationConfig, world_T_phone_true: FloatArray, rng: np.random.Generator
) -> list[tuple[str, int, FloatArray]]:
    """(name, pose index, phone_T_poi) for each point of interest, at distinct random poses."""
    n = world_T_phone_true.shape[0]
    count = min(config.num_points_of_interest, n - 1)  # the app's pose_id + 1 must exist
    indices = np.sort(rng.choice(n - 1, size=count, replace=False)).tolist()
    phone_T_poi = np.eye(4)
    phone_T_poi[:3, 3] = POI_OFFSET_PHONE_M
    names = [
        POI_NAMES[k % len(POI_NAMES)]
        + (f" ({k // len(POI_NAMES) + 1})" if k >= len(POI_NAMES) else "")
        for k in range(count)
    ]
    return [(name, int(i), phone_T_poi.copy()) for name, i in zip(names, indices, strict=True)]


# --------------------------------------------------------------------------- upload


def upload_document(
    config: SimulationConfig,
    world_T_phone_odometry: FloatArray,
    pose_index: IntArray,
    tag_id: IntArray,
    detections: Measurements,
    pois: list[tuple[str, int, FloatArray]],
) -> dict[str, Any]:
    """The app's JSON object (architecture §2) from the arrays; plain Python numbers throughout."""
    n = world_T_phone_odometry.shape[0]
    timestamp_s = START_TIME_S + np.arange(n) / config.rate_hz
    timestamps = timestamp_s.tolist()
    poses_column_major = np.swapaxes(world_T_phone_odometry, 1, 2).reshape(n, 16).tolist()
    pose_data = [
        {"id": i, "timestamp": timestamps[i], "pose": poses_column_major[i], "planes": []}
        for i in range(n)
    ]

    m = pose_index.shape[0]
    covariance = detections.joint_covariance
    position_variance = np.diagonal(covariance, axis1=1, axis2=2)[:, :3].tolist()
    orientation_variance = np.diagonal(covariance, axis1=1, axis2=2)[:, 3:].tolist()
    tag_poses = detections.camera_T_tag.reshape(m, 16).tolist()  # row-major
    corners = detections.corners_px.reshape(m, 8).tolist()
    joint = covariance.reshape(m, 49).tolist()
    intrinsics = [float(v) for v in config.camera_intrinsics]
    pose_ids = pose_index.tolist()
    tag_ids = tag_id.tolist()

    tag_data: list[list[dict[str, Any]]] = []
    for row in range(m):
        detection = {
            "tag_id": tag_ids[row],
            "pose_id": pose_ids[row],
            "timestamp": timestamps[pose_ids[row]],
            "tag_pose": tag_poses[row],
            "camera_intrinsics": list(intrinsics),
            "tag_corners_pixel_coordinates": corners[row],
            "tag_position_variance": position_variance[row],
            "tag_orientation_variance": orientation_variance[row],
            "joint_covar": joint[row],
        }
        if row > 0 and pose_ids[row] == pose_ids[row - 1]:
            tag_data[-1].append(detection)  # several tags in one camera frame
        else:
            tag_data.append([detection])

    location_data = [
        {
            "name": name,
            "pose_id": i + 1,  # the app writes the id of the *next* pose
            "timestamp": timestamps[i],
            "transform": phone_T_poi.reshape(16).tolist(),  # row-major
        }
        for name, i, phone_T_poi in pois
    ]
    return {
        "map_id": config.map_id,
        "pose_data": pose_data,
        "tag_data": tag_data,
        "location_data": location_data,
        "plane_data": [],
    }
