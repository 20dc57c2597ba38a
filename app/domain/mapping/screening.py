"""Screening tag detections before they enter the factor graph.

A detection is rejected, with its reason, when

- its **corners do not agree with its pose** (``reprojection``): the tag's corners, projected from
  ``camera_T_tag`` with the camera intrinsics, lie far from the detected corner pixels;
- it was seen at a **grazing angle** (``view_angle``): the angle between the tag's normal (+z, out
  of the wall) and the line from the tag to the camera is large, where PnP orientation is poor;
- it is **far** (``distance``): the camera-to-tag distance exceeds the limit.

Tag size. Some real sessions' ``tag_pose`` is consistent with a tag side other than the configured
one (``floor_2_straight``: every pose implies ≈0.149 m where the tags are nominally 0.173 m; the
size the app assumed, not the tag, sets the depth). A consistent mismatch is not a bad detection,
so the reprojection test fits one *effective side* per tag (the median over its detections of the
side that best explains the corner spread) and measures each detection against it. A detection
whose depth disagrees with the other detections of its tag still fails. The mismatch itself is
reported as a warning.

Bursts. A burst of k sightings of one tag (consecutive sightings less than ``BURST_GAP_S`` apart:
one viewpoint, one PnP bias) is not k independent measurements: each of its sightings weighs as
if its variance were k^``BURST_WEIGHT_POWER`` times larger (:func:`burst_variance_scale`), so a
walk that lingers at each tag does not outvote one that passes by.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from app.domain.frames import FloatArray, project_pinhole_px, tag_corners_in_camera
from app.domain.mapping.map_result import Rejection
from app.domain.mapping.params import SlamParams
from app.domain.upload.session import TagDetections

BoolArray = npt.NDArray[np.bool_]

#: Warn when a tag's effective side differs from the configured one by more than this fraction.
SIZE_MISMATCH_WARNING_FRACTION = 0.05
#: Sightings of one tag less than this apart (s) are one burst (``sighting_burst_sizes``).
BURST_GAP_S = 3.0
#: A burst of k sightings weighs as k^(1 − power) sightings (each one's variance × k^power): 0.5,
#: between independent sightings (0: best on simulated walks, whose noise is drawn independently
#: per sighting) and fully correlated ones (1: best on the real mac-building walks);
#: docs/multi-session.md has both ends' numbers.
BURST_WEIGHT_POWER = 0.5


@dataclass(frozen=True, slots=True, kw_only=True)
class DetectionGeometry:
    """Per-detection measurements (M rows) the screening tests use.

    distance_m: camera-to-tag-centre distance, m.
    view_angle_deg: angle between the tag normal and the tag→camera line, deg.
    effective_size_m: the tag side that best explains each detection's corner spread, m.
    reprojection_px: RMS corner error with the tag's median effective side, px.
    """

    distance_m: FloatArray
    view_angle_deg: FloatArray
    effective_size_m: FloatArray
    reprojection_px: FloatArray


@dataclass(frozen=True, slots=True, kw_only=True)
class Screening:
    """The outcome: ``used`` (M,) mask, the rejections, and warnings for the map."""

    used: BoolArray
    rejections: tuple[Rejection, ...]
    geometry: DetectionGeometry
    warnings: tuple[str, ...]


def project_tag_corners(detections: TagDetections, size_m: FloatArray) -> FloatArray:
    """(M, 4, 2) pixel positions of each detection's corners from its ``camera_T_tag``."""
    corners_camera = tag_corners_in_camera(detections.camera_T_tag, size_m)
    return project_pinhole_px(corners_camera, detections.intrinsics[:, None, :])


def measure_detections(detections: TagDetections, params: SlamParams) -> DetectionGeometry:
    """Distance, view angle, effective tag side and reprojection error of every detection."""
    m = len(detections)
    camera_t_tag = detections.camera_T_tag[:, :3, 3]
    distance_m = np.linalg.norm(camera_t_tag, axis=1)
    normal_camera = detections.camera_T_tag[:, :3, 2]
    to_camera = -camera_t_tag / np.maximum(distance_m, 1e-12)[:, None]
    cos_angle = np.clip(np.einsum("mi,mi->m", normal_camera, to_camera), -1.0, 1.0)
    view_angle_deg = np.degrees(np.arccos(cos_angle))

    nominal_m = np.array([params.tag_size_for(int(t)) for t in detections.tag_id], dtype=float)
    if m == 0:
        empty = np.empty(0)
        return DetectionGeometry(
            distance_m=distance_m,
            view_angle_deg=view_angle_deg,
            effective_size_m=empty,
            reprojection_px=empty,
        )
    projected = project_tag_corners(detections, nominal_m)
    spread_projected = _corner_spread_px(projected)
    spread_detected = _corner_spread_px(detections.corners_px)
    effective_size_m = nominal_m * spread_detected / np.maximum(spread_projected, 1e-9)

    tag_size_m = np.empty(m)
    for tag_id in np.unique(detections.tag_id):
        rows = detections.tag_id == tag_id
        tag_size_m[rows] = np.median(effective_size_m[rows])
    reprojected = project_tag_corners(detections, tag_size_m)
    error_px = np.linalg.norm(reprojected - detections.corners_px, axis=2)
    reprojection_px = np.sqrt(np.mean(error_px**2, axis=1))
    return DetectionGeometry(
        distance_m=distance_m,
        view_angle_deg=view_angle_deg,
        effective_size_m=effective_size_m,
        reprojection_px=reprojection_px,
    )


def screen_detections(detections: TagDetections, params: SlamParams) -> Screening:
    """Which detections enter the graph, and why the others do not."""
    geometry = measure_detections(detections, params)
    tests = (
        ("reprojection", geometry.reprojection_px, params.max_reprojection_px),
        ("view_angle", geometry.view_angle_deg, params.max_view_angle_deg),
        ("distance", geometry.distance_m, params.max_distance_m),
    )
    used = np.ones(len(detections), dtype=bool)
    rejections = []
    for row in range(len(detections)):
        for reason, values, limit in tests:
            if values[row] > limit:
                used[row] = False
                rejections.append(
                    Rejection(
                        detection_index=row,
                        tag_id=int(detections.tag_id[row]),
                        pose_index=int(detections.pose_index[row]),
                        reason=reason,
                        value=float(values[row]),
                        limit=float(limit),
                    )
                )
                break
    return Screening(
        used=used,
        rejections=tuple(rejections),
        geometry=geometry,
        warnings=tuple(_size_warnings(detections, geometry, used)),
    )


def _corner_spread_px(corners_px: FloatArray) -> FloatArray:
    """(M,) mean distance of the 4 corners from their centroid, px."""
    centred = corners_px - corners_px.mean(axis=1, keepdims=True)
    return np.asarray(np.linalg.norm(centred, axis=2).mean(axis=1), dtype=np.float64)


def _size_warnings(
    detections: TagDetections, geometry: DetectionGeometry, used: BoolArray
) -> list[str]:
    """One line when the tags in the map disagree on their side: those whose used detections
    imply a side more than :data:`SIZE_MISMATCH_WARNING_FRACTION` from the map's typical one
    (the median over its tags). A side that every tag shares, even one other than configured,
    says nothing wrong with the map (the poses are used as given; docs/architecture.md, "Screening
    first"), and a tag left out of the map cannot distort it: neither is warned about."""
    sides_m: dict[int, float] = {}  # tag id → median effective side of its used detections, m
    for tag_id in np.unique(detections.tag_id[used]):
        rows = (detections.tag_id == tag_id) & used
        sides_m[int(tag_id)] = float(np.median(geometry.effective_size_m[rows]))
    if len(sides_m) < 2:
        return []
    typical_m = float(np.median(list(sides_m.values())))
    odd = sorted(
        t
        for t, side_m in sides_m.items()
        if abs(side_m / typical_m - 1.0) > (SIZE_MISMATCH_WARNING_FRACTION)
    )
    if not odd:
        return []
    odd_m = [sides_m[t] for t in odd]
    rest_m = [side_m for t, side_m in sides_m.items() if t not in odd]
    what = (
        f"tag {odd[0]}'s detections imply"
        if len(odd) == 1
        else (f"{len(odd)} tags' detections (tags {_id_list(odd)}) imply")
    )
    shown = f"{odd_m[0]:.3f} m" if len(odd) == 1 else f"{min(odd_m):.3f}–{max(odd_m):.3f} m"
    others = (
        f"the map's other {len(rest_m)} tags {np.median(rest_m):.3f} m"
        if rest_m
        else f"the map's tags range over {min(odd_m):.3f}–{max(odd_m):.3f} m"
    )
    return [
        f"{what} a tag side of {shown}, {others}: their distances from the phone are on another "
        "scale than the others', which distorts the map where they are. Check that every tag "
        "is printed at one size and the app set to that size; no parameter corrects this."
    ]


def _id_list(ids: list[int], limit: int = 12) -> str:
    shown = ", ".join(str(i) for i in ids[:limit])
    return shown + (f" and {len(ids) - limit} more" if len(ids) > limit else "")


def sighting_burst_sizes(detections: TagDetections, used: BoolArray) -> FloatArray:
    """(M,) for each used detection, how many used sightings of its tag its *burst* holds: the
    sightings of one tag with no gap longer than ``BURST_GAP_S`` between consecutive ones (the
    phone looking at the tag for a while, from about one place); 1 for unused detections.
    desnat_straight_once lingers at each tag (10 sightings per burst), floor_2_straight passes by
    (1.1)."""
    size = np.ones(len(detections))
    rows_used = np.flatnonzero(used)
    for tag_id in np.unique(detections.tag_id[rows_used]):
        rows = rows_used[detections.tag_id[rows_used] == tag_id]
        order = np.argsort(detections.timestamp_s[rows], kind="stable")
        rows = rows[order]
        burst = np.concatenate(
            [[0], np.cumsum(np.diff(detections.timestamp_s[rows]) > BURST_GAP_S)]
        )
        counts = np.bincount(burst)
        size[rows] = counts[burst]
    return size


def burst_variance_scale(detections: TagDetections, used: BoolArray) -> FloatArray:
    """(M,) the factor on each detection's tag variance for its burst: k^``BURST_WEIGHT_POWER``
    (module docstring)."""
    return np.asarray(
        np.power(sighting_burst_sizes(detections, used), BURST_WEIGHT_POWER), dtype=np.float64
    )
