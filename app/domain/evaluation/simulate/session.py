"""A simulated session and its entry points: :class:`SimulatedSession`, ``simulate_session``,
``record_walk`` (one walk through a given building) and ``simulate_along_trajectory``."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from app.domain.errors import ParameterError
from app.domain.evaluation.ground_truth import ground_truth_to_json
from app.domain.frames import PHONE_T_CAMERA_CV, FloatArray, se3_inverse

from .building import Building, build_building
from .config import APPROACH_GAP_S, BoolArray, IntArray, SimulationConfig
from .detections import approach_ids, first_of_each, measure_detections, visible_pairs
from .odometry import drift_odometry
from .upload import points_of_interest_of, upload_document
from .walk import walk_route


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class SimulatedSession:
    """A simulated mapping session: the upload the app would send, and the truth behind it.

    upload: the app's JSON object (architecture §2), ready for ``json.dumps`` or ``parse_session``.
    world_T_phone_true: (N, 4, 4) true phone poses, world frame y up, m.
    world_T_phone_odometry: (N, 4, 4) the drifting odometry written to ``pose_data`` (same frame at
        the first pose).
    world_T_tag_true: tag id → (4, 4) true tag pose, for every tag in the building (seen or not).
    world_T_poi_true: name → (4, 4) true pose of each point of interest.
    detection_tag_id, detection_pose_index: (M,) each detection in upload order; the pose index is
        the row of ``pose_data`` (equal to its ``id``).
    camera_T_tag_true: (M, 4, 4) the true pose behind each detection, OpenCV camera convention.
    detection_is_outlier: (M,) True where ``tag_pose`` was made grossly wrong on purpose.
    """

    config: SimulationConfig
    upload: dict[str, Any]
    world_T_phone_true: FloatArray
    world_T_phone_odometry: FloatArray
    world_T_tag_true: dict[int, FloatArray]
    world_T_poi_true: dict[str, FloatArray]
    detection_tag_id: IntArray
    detection_pose_index: IntArray
    camera_T_tag_true: FloatArray
    detection_is_outlier: BoolArray
    building: Building = field(repr=False)

    @property
    def detected_tag_ids(self) -> list[int]:
        """Distinct ids of the tags detected at least once, sorted."""
        return sorted({int(t) for t in self.detection_tag_id})

    def path_length_m(self) -> float:
        """Distance walked by the phone (true trajectory), m."""
        steps = np.diff(self.world_T_phone_true[:, :3, 3], axis=0)
        return float(np.linalg.norm(steps, axis=1).sum())

    def odometry_end_error_m(self) -> float:
        """Distance between the odometry's and the truth's last positions, m (the drift)."""
        end = self.world_T_phone_odometry[-1, :3, 3] - self.world_T_phone_true[-1, :3, 3]
        return float(np.linalg.norm(end))

    def ground_truth_json(self, *, detected_only: bool = False) -> dict[str, Any]:
        """The ground-truth file form, ``{"poses": [{"tag_id": N, "pose": [x,y,z,qx,qy,qz,qw]}]}``.

        Every tag of the building, or with ``detected_only`` only those the session saw.
        """
        ids = self.detected_tag_ids if detected_only else sorted(self.world_T_tag_true)
        return ground_truth_to_json({tag_id: self.world_T_tag_true[tag_id] for tag_id in ids})

    def __str__(self) -> str:
        return (
            f"{self.config.map_id}: {self.world_T_phone_true.shape[0]} poses, "
            f"{self.path_length_m():.1f} m walked, {self.detection_tag_id.shape[0]} detections "
            f"of {len(self.detected_tag_ids)} tags ({len(self.world_T_tag_true)} in the building), "
            f"odometry drift {self.odometry_end_error_m():.2f} m at the end"
        )


# --------------------------------------------------------------------------- entry point


def simulate_session(config: SimulationConfig) -> SimulatedSession:
    """Simulate a mapping session; deterministic for a given config (and its seed)."""
    streams = np.random.SeedSequence(config.seed).spawn(6)
    rng_building, rng_walk, rng_odometry, rng_tags, rng_outliers, rng_poi = (
        np.random.default_rng(s) for s in streams
    )
    building = build_building(config, rng_building)
    return record_walk(config, building, (rng_walk, rng_odometry, rng_tags, rng_outliers, rng_poi))


def record_walk(
    config: SimulationConfig,
    building: Building,
    rngs: tuple[
        np.random.Generator,
        np.random.Generator,
        np.random.Generator,
        np.random.Generator,
        np.random.Generator,
    ],
    *,
    world_T_upload: FloatArray | None = None,
) -> SimulatedSession:
    """One walk through ``building`` as the app records it, drawing from ``rngs`` (walk,
    odometry, tag measurements, outliers, points of interest). ``world_T_upload``: the pose of
    the building in the frame the phone's odometry is uploaded in (identity when None); the
    truth stays in the building's frame."""
    rng_walk, rng_odometry, rng_tags, rng_outliers, rng_poi = rngs
    world_T_phone_true = walk_route(config, building, rng_walk)
    world_T_phone_odometry = drift_odometry(config, world_T_phone_true, rng_odometry)

    tag_ids = np.array(sorted(building.world_T_tag), dtype=np.int64)
    world_T_tags = np.stack([building.world_T_tag[int(t)] for t in tag_ids])
    pose_index, tag_row = visible_pairs(config, building, world_T_phone_true, world_T_tags)
    approach = approach_ids(pose_index, tag_row, round(APPROACH_GAP_S * config.rate_hz))
    if config.sightings_per_approach:
        keep = first_of_each(approach, config.sightings_per_approach)
        pose_index, tag_row, approach = pose_index[keep], tag_row[keep], approach[keep]
    camera_T_tag_true = (
        PHONE_T_CAMERA_CV @ se3_inverse(world_T_phone_true[pose_index]) @ world_T_tags[tag_row]
    )
    detections = measure_detections(
        config, camera_T_tag_true, rng_tags, rng_outliers, approach=approach
    )
    pois = points_of_interest_of(config, world_T_phone_true, rng_poi)

    uploaded_odometry = (
        world_T_phone_odometry
        if world_T_upload is None
        else world_T_upload @ world_T_phone_odometry
    )
    upload = upload_document(
        config,
        uploaded_odometry,
        pose_index,
        tag_ids[tag_row],
        detections,
        pois,
    )
    return SimulatedSession(
        config=config,
        upload=upload,
        world_T_phone_true=world_T_phone_true,
        world_T_phone_odometry=world_T_phone_odometry,
        world_T_tag_true=dict(building.world_T_tag),
        world_T_poi_true={
            name: world_T_phone_true[i] @ phone_T_poi for name, i, phone_T_poi in pois
        },
        detection_tag_id=tag_ids[tag_row],
        detection_pose_index=pose_index,
        camera_T_tag_true=camera_T_tag_true,
        detection_is_outlier=detections.is_outlier,
        building=building,
    )


def simulate_along_trajectory(
    config: SimulationConfig,
    world_T_phone_true: FloatArray,
    world_T_tag_true: dict[int, FloatArray],
    detection_pose_index: IntArray,
    detection_tag_id: IntArray,
) -> SimulatedSession:
    """A session along a given true trajectory, seeing given tags at given poses (the paper's
    simulation: the truth is a real session's *optimized* map, the detections its used ones).

    Odometry drift and tag-measurement noise come from ``config`` (and its seed) as in
    :func:`simulate_session`; ``config.num_poses`` and ``rate_hz`` must match the trajectory
    (``detection_pose_index`` in upload order, i.e. non-decreasing). No points of interest.
    """
    n = world_T_phone_true.shape[0]
    if config.num_poses != n:
        raise ParameterError(f"config.num_poses is {config.num_poses}, the trajectory has {n}")
    order = np.asarray(detection_pose_index, dtype=np.int64)
    if order.size and (np.any(np.diff(order) < 0) or order[0] < 0 or order[-1] >= n):
        raise ParameterError("detection_pose_index must be non-decreasing pose rows")
    streams = np.random.SeedSequence(config.seed).spawn(6)
    _, _, rng_odometry, rng_tags, rng_outliers, _ = (np.random.default_rng(s) for s in streams)
    world_T_phone_odometry = drift_odometry(config, world_T_phone_true, rng_odometry)
    tag_ids = np.asarray(detection_tag_id, dtype=np.int64)
    world_T_tags = (
        np.stack([world_T_tag_true[int(t)] for t in tag_ids])
        if tag_ids.size
        else (np.empty((0, 4, 4)))
    )
    camera_T_tag_true = PHONE_T_CAMERA_CV @ se3_inverse(world_T_phone_true[order]) @ world_T_tags
    detections = measure_detections(config, camera_T_tag_true, rng_tags, rng_outliers)
    upload = upload_document(config, world_T_phone_odometry, order, tag_ids, detections, [])
    return SimulatedSession(
        config=config,
        upload=upload,
        world_T_phone_true=world_T_phone_true,
        world_T_phone_odometry=world_T_phone_odometry,
        world_T_tag_true=dict(world_T_tag_true),
        world_T_poi_true={},
        detection_tag_id=tag_ids,
        detection_pose_index=order,
        camera_T_tag_true=camera_T_tag_true,
        detection_is_outlier=detections.is_outlier,
        building=Building(
            node_xyz_m=np.empty((0, 3)),
            edge_nodes=np.empty((0, 2), dtype=np.int64),
            edge_polylines_m=(),
            free_space_boxes_m=np.empty((0, 2, 3)),
            world_T_tag=dict(world_T_tag_true),
            corridor_tag_ids=(),
            tag_offset_along_m={},
            floor_heights_m=(),
        ),
    )
