"""Maps to and from JSON: our own lossless form, and the app's download format (architecture §7).

    document = map_to_json(result)          # ours: everything in MapResult, round-trips
    result = map_from_json(document)
    app_map = map_to_app_format(result)     # what the iPhone app downloads
    app_map = map_to_app_format(result, path_graph=pg)   # … with the path graph's links
    app_map = app_map_as_served(result, path_graph=pg)   # … byte for byte as the server has it

Poses are written as ``[x, y, z, qx, qy, qz, qw]`` (metres, unit quaternion), map frame y up.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from app.domain.errors import InvisibleMapError, MapFormatError
from app.domain.frames import (
    FloatArray,
    pose_from_xyz_quat_xyzw,
    pose_to_xyz_quat_xyzw,
    poses_to_xyz_quat_xyzw,
)
from app.domain.mapping.keyframes import keyframe_spans
from app.domain.mapping.map_result import FactorResiduals, MapResult, OptimizationStats, Rejection
from app.domain.mapping.noise import noise_estimate_from_dict
from app.domain.mapping.params import SlamParams
from app.domain.navigation.path_graph import (
    PathGraph,
    app_links,
    chain_links,
    unique_waypoint_names,
)
from app.domain.navigation.path_graph.app_format import MAX_APP_POSES, thinned_rows, thinning_note

MAP_FORMAT = "invisible-map/map"
MAP_FORMAT_VERSION = 1


def map_to_json(result: MapResult) -> dict[str, Any]:
    """Our map document: tags, trajectory, points of interest, parameters, statistics, residuals."""
    residuals = result.residuals
    return {
        "format": MAP_FORMAT,
        "format_version": MAP_FORMAT_VERSION,
        "map_id": result.map_id,
        "params": result.params.to_dict(),
        "stats": {
            "iterations": result.stats.iterations,
            "start_iterations": result.stats.start_iterations,
            "initial_error": result.stats.initial_error,
            "final_error": result.stats.final_error,
            "build_ms": result.stats.build_ms,
            "optimize_ms": result.stats.optimize_ms,
            "marginals_ms": result.stats.marginals_ms,
            "num_factors": result.stats.num_factors,
            "num_variables": result.stats.num_variables,
            "detections_used": result.detections_used,
            "detections_rejected": len(result.rejections),
        },
        "tags": [
            {
                "id": int(tag_id),
                "pose": pose_to_xyz_quat_xyzw(result.world_T_tag[k]),
                "pose_pre_optimized": pose_to_xyz_quat_xyzw(result.world_T_tag_pre[k]),
                "covariance_rot_rad_trans_m": _nan_to_none(result.tag_covariance[k]),
                "detections": int(result.tag_detection_count[k]),
            }
            for k, tag_id in enumerate(result.tag_ids)
        ],
        "trajectory": {
            "pose_id": result.pose_id.tolist(),
            "timestamp_s": result.timestamp_s.tolist(),
            "pose_xyz_quat_xyzw": poses_to_xyz_quat_xyzw(result.world_T_phone).tolist(),
        },
        "points_of_interest": [
            {"name": name, "pose": pose_to_xyz_quat_xyzw(result.world_T_poi[k])}
            for k, name in enumerate(result.poi_names)
        ],
        "rejections": [
            {
                "detection_index": r.detection_index,
                "tag_id": r.tag_id,
                "pose_index": r.pose_index,
                "reason": r.reason,
                "value": r.value,
                "limit": r.limit,
                "detail": r.detail,
            }
            for r in result.rejections
        ],
        "residuals": {
            "keyframe_index": residuals.keyframe_index.tolist(),
            "odometry_chi2": residuals.odometry_chi2.tolist(),
            "gravity_chi2": residuals.gravity_chi2.tolist(),
            "tag_chi2": residuals.tag_chi2.tolist(),
            "tag_detection_index": residuals.tag_detection_index.tolist(),
            "tag_pose_index": residuals.tag_pose_index.tolist(),
            "tag_translation_m": residuals.tag_translation_m.tolist(),
            "tag_rotation_rad": residuals.tag_rotation_rad.tolist(),
        },
        "warnings": list(result.warnings),
        # the walk's noise as its residuals support it (issue 25); absent in older documents
        "noise": None if result.noise is None else result.noise.to_dict(result.params),
    }


def map_from_json(document: Any) -> MapResult:
    """Read back a document written by :func:`map_to_json`."""
    if not isinstance(document, Mapping) or document.get("format") != MAP_FORMAT:
        raise MapFormatError(f"not an {MAP_FORMAT} document")
    if document.get("format_version") != MAP_FORMAT_VERSION:
        raise MapFormatError(
            f"unsupported format_version {document.get('format_version')!r}, "
            f"this build reads {MAP_FORMAT_VERSION}"
        )
    try:
        tags = document["tags"]
        trajectory = document["trajectory"]
        stats = document["stats"]
        residuals = document["residuals"]
        pois = document["points_of_interest"]
        return MapResult(
            map_id=str(document["map_id"]),
            # maps stored before keyframes had every pose in the graph
            params=SlamParams.from_dict({"keyframe_interval_s": 0.0, **document["params"]}),
            pose_id=np.asarray(trajectory["pose_id"], dtype=np.int64),
            timestamp_s=np.asarray(trajectory["timestamp_s"], dtype=np.float64),
            world_T_phone=_poses(trajectory["pose_xyz_quat_xyzw"]),
            tag_ids=np.asarray([t["id"] for t in tags], dtype=np.int64),
            world_T_tag=_poses([t["pose"] for t in tags]),
            world_T_tag_pre=_poses([t["pose_pre_optimized"] for t in tags]),
            tag_covariance=np.asarray(
                [_none_to_nan(t["covariance_rot_rad_trans_m"]) for t in tags], dtype=np.float64
            ).reshape(-1, 6, 6),
            tag_detection_count=np.asarray([t["detections"] for t in tags], dtype=np.int64),
            detections_used=int(stats["detections_used"]),
            rejections=tuple(
                Rejection(
                    detection_index=int(r["detection_index"]),
                    tag_id=int(r["tag_id"]),
                    pose_index=int(r["pose_index"]),
                    reason=str(r["reason"]),
                    value=float(r["value"]),
                    limit=float(r["limit"]),
                )
                for r in document["rejections"]
            ),
            residuals=FactorResiduals(
                keyframe_index=np.asarray(
                    residuals.get("keyframe_index", range(len(trajectory["pose_id"]))),
                    dtype=np.int64,
                ),
                odometry_chi2=np.asarray(residuals["odometry_chi2"], dtype=np.float64),
                gravity_chi2=np.asarray(residuals["gravity_chi2"], dtype=np.float64),
                tag_chi2=np.asarray(residuals["tag_chi2"], dtype=np.float64),
                tag_detection_index=np.asarray(residuals["tag_detection_index"], dtype=np.int64),
                tag_pose_index=np.asarray(residuals["tag_pose_index"], dtype=np.int64),
                tag_translation_m=np.asarray(residuals["tag_translation_m"], dtype=np.float64),
                tag_rotation_rad=np.asarray(residuals["tag_rotation_rad"], dtype=np.float64),
            ),
            stats=OptimizationStats(
                iterations=int(stats["iterations"]),
                start_iterations=int(stats.get("start_iterations", 0)),
                initial_error=float(stats["initial_error"]),
                final_error=float(stats["final_error"]),
                build_ms=float(stats["build_ms"]),
                optimize_ms=float(stats["optimize_ms"]),
                marginals_ms=float(stats["marginals_ms"]),
                num_factors=int(stats["num_factors"]),
                num_variables=int(stats["num_variables"]),
            ),
            poi_names=tuple(str(p["name"]) for p in pois),
            world_T_poi=_poses([p["pose"] for p in pois]),
            warnings=tuple(str(w) for w in document.get("warnings", [])),
            noise=(
                None
                if document.get("noise") is None
                else noise_estimate_from_dict(document["noise"])
            ),
        )
    except InvisibleMapError as err:
        raise MapFormatError(f"map document: {err}") from err
    except (KeyError, TypeError, ValueError) as err:
        raise MapFormatError(f"map document is missing or has a malformed {err}") from err


def map_to_app_format(
    result: MapResult, *, path_graph: PathGraph | None = None, max_poses: int = MAX_APP_POSES
) -> dict[str, Any]:
    """The app's download format (docs/architecture.md §7), made so the app can neither fail to
    decode it nor crash planning a route on it (``app.domain.formats.app_model`` models the app's
    rules).

    ``adjChi2`` of a pose is the chi² of the odometry factors touching it (a pose between two
    keyframes: the factor spanning it); ``vizTags`` the number of tag detections used from it.
    ``neighbors`` (:func:`app.domain.navigation.path_graph.app_links`): with ``path_graph`` (built
    from this ``result``), its links, listed at both ends, of its largest connected part; graph
    nodes that are no pose are extra odometry vertices with ``poseId`` = max pose id + 1, + 2, …
    (node-id order), their position, an identity rotation, ``adjChi2`` and ``vizTags`` 0; a pose
    that is no node is linked to both ends of its nearest edge, and poses of a part that is not
    connected to the largest are left out. Without ``path_graph``: the chain of poses. Of a walk of
    more than ``max_poses`` poses only every k-th is listed (graph nodes that are poses all the
    same: :func:`app.domain.navigation.path_graph.app_format.thinned_rows`), so that the file holds
    the navigation graph, not every pose, and stays far under the app's 10 MiB cap. Waypoints with
    one name are made unique ("Desk", "Desk (2)").

    ``notes`` (an extra key, which the app ignores) says what was changed for the app: a walk
    that falls apart, renamed waypoints.
    """
    n = result.world_T_phone.shape[0]
    adjacent_chi2 = _adjacent_odometry_chi2(n, result.residuals)
    visible_tags = np.bincount(result.residuals.tag_pose_index, minlength=n).astype(float)
    pose_ids = result.pose_id.tolist()
    pose_rows = thinned_rows(n, max_poses)
    if path_graph is None:
        links = chain_links(pose_ids, pose_rows=pose_rows)
    else:
        links = app_links(
            path_graph.graph,
            floor_levels_m=path_graph.floor_levels_m,
            pose_id=result.pose_id,
            positions_m=result.world_T_phone[:, :3, 3],
            pose_rows=pose_rows,
        )
    waypoint_names, renamed = unique_waypoint_names(list(result.poi_names))
    linked = [i for i, neighbors in enumerate(links.neighbors) if neighbors is not None]
    linked_rows = poses_to_xyz_quat_xyzw(result.world_T_phone[linked]).tolist()
    return {
        "tag_vertices": [
            {"id": int(tag_id), **_translation_rotation(result.world_T_tag[k])}
            for k, tag_id in enumerate(result.tag_ids)
        ],
        "odometry_vertices": [
            {
                "poseId": int(pose_ids[i]),
                **_translation_rotation_of(row),
                "adjChi2": float(adjacent_chi2[i]),
                "vizTags": float(visible_tags[i]),
                "neighbors": links.neighbors[i],
            }
            for i, row in zip(linked, linked_rows, strict=True)
        ]
        + [
            {
                "poseId": vertex.pose_id,
                **_translation_rotation(_pose_at(vertex.position_m)),
                "adjChi2": 0.0,
                "vizTags": 0.0,
                "neighbors": vertex.neighbors,
            }
            for vertex in links.extra
        ],
        "waypoints_vertices": [
            {"id": name, **_translation_rotation(result.world_T_poi[k])}
            for k, name in enumerate(waypoint_names)
        ],
        "notes": [*links.notes, *thinning_note(n, len(pose_rows)), *renamed],
    }


def app_map_as_served(result: MapResult, *, path_graph: PathGraph | None) -> dict[str, Any]:
    """The app-map exactly as the server serves the version stored from ``result``: the server
    stores poses as position + quaternion (:func:`map_to_json`), and a rotation read back from a
    quaternion differs from the optimizer's in its last bits, so the CLI writes the same
    document through the same round trip."""
    return map_to_app_format(map_from_json(map_to_json(result)), path_graph=path_graph)


def _adjacent_odometry_chi2(n: int, residuals: FactorResiduals) -> FloatArray:
    """(n,) per pose: the chi² of the odometry factors touching it (a keyframe), or of the one
    spanning it (a pose between keyframes)."""
    keyframes, chi2 = residuals.keyframe_index, residuals.odometry_chi2
    adjacent = np.zeros(n)
    if keyframes.size < 2:
        return adjacent
    span = keyframe_spans(keyframes, n)
    between = ~np.isin(np.arange(n), keyframes)
    adjacent[between] = chi2[span[between]]
    np.add.at(adjacent, keyframes[1:], chi2)
    np.add.at(adjacent, keyframes[:-1], chi2)
    return adjacent


def save_json(document: Any, path: str | Path) -> None:
    """Write ``document`` as JSON, atomically (a temporary file renamed into place)."""
    path = Path(path)
    temporary = path.with_name(f".{path.name}.tmp")
    temporary.write_text(json.dumps(document, separators=(",", ":"), allow_nan=False))
    temporary.replace(path)


def _translation_rotation(T: FloatArray) -> dict[str, dict[str, float]]:
    return _translation_rotation_of(pose_to_xyz_quat_xyzw(T))


def _translation_rotation_of(xyz_quat_xyzw: Sequence[float]) -> dict[str, dict[str, float]]:
    x, y, z, qx, qy, qz, qw = (float(v) for v in xyz_quat_xyzw)
    return {
        "translation": {"x": x, "y": y, "z": z},
        "rotation": {"x": qx, "y": qy, "z": qz, "w": qw},
    }


def _pose_at(position_m: Sequence[float]) -> FloatArray:
    """(4, 4) the pose with identity rotation at ``position_m``."""
    T = np.eye(4)
    T[:3, 3] = position_m
    return T


def _poses(rows: Sequence[Sequence[float]]) -> FloatArray:
    if len(rows) == 0:
        return np.empty((0, 4, 4))
    return np.stack([pose_from_xyz_quat_xyzw(row) for row in rows])


def _nan_to_none(matrix: FloatArray) -> list[list[float | None]]:
    return [[None if np.isnan(v) else float(v) for v in row] for row in matrix]


def _none_to_nan(rows: Sequence[Sequence[float | None]]) -> list[list[float]]:
    return [[np.nan if v is None else float(v) for v in row] for row in rows]
