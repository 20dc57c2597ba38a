"""Step 1, each walk alone: its tag depth scale, its own map and its noise.

Each walk is screened on its own (its tags' effective side from its own sightings), its tag depth
scale estimated from its own sightings (:func:`tag_depth_scale`), and optimized alone with its
noise estimated from its own residuals (``noise.py``: variance-component estimation;
``params.estimate_noise``) by :func:`fit_walk`. This is the walk's own map and its noise: a walk's
weight in the building comes from its own data, not from the others'.

Also the session edits a build of several walks uses: :func:`scaled_tag_depths`,
:func:`keep_poses` (a floor of a walk) and :func:`sighting_burst_sizes`.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from app.domain.frames import FloatArray
from app.domain.mapping.joint.model import BoolArray, WalkFit
from app.domain.mapping.params import SlamParams
from app.domain.mapping.screening import Screening
from app.domain.mapping.screening import sighting_burst_sizes as _burst_sizes
from app.domain.mapping.slam import GraphInputs, chain_costs, map_result, solve
from app.domain.upload.session import Session, TagDetections

#: Parallax (Σ‖Δ camera-to-tag vector‖² over pairs of sightings of a tag) below which a session's
#: tag depth scale is not estimated, m².
MIN_SCALE_PARALLAX_M2 = 1.0


#: A depth scale closer to 1 than this is noise (±3% on simulated walks whose sizes are right); the
#: poses are used as given.
MIN_DEPTH_SCALE_CHANGE = 0.05


#: Sightings of a tag further apart in time than this are not compared for the scale (VIO drift), s.
SCALE_PAIR_WINDOW_S = 15.0


def tag_depth_scale(session: Session, used: BoolArray | None = None) -> float:
    """The factor on the session's camera-to-tag translations that makes its sightings of each
    tag, from different places within ``SCALE_PAIR_WINDOW_S``, agree best given its odometry
    (least squares over pairs of sightings), or 1.0 when the pairs' parallax is below
    ``MIN_SCALE_PARALLAX_M2`` (the data cannot tell) or the factor is within
    ``MIN_DEPTH_SCALE_CHANGE`` of 1."""
    scale, parallax_m2 = tag_depth_fit(session, used)
    if parallax_m2 < MIN_SCALE_PARALLAX_M2:
        return 1.0
    return scale if abs(scale - 1.0) > MIN_DEPTH_SCALE_CHANGE else 1.0


def tag_depth_fit(session: Session, used: BoolArray | None = None) -> tuple[float, float]:
    """:func:`tag_depth_scale`'s least-squares factor, whatever its size (1.0 without pairs),
    and the parallax it rests on: Σ‖Δ camera-to-tag vector‖² over the pairs of sightings, m²."""
    detections = session.detections
    rows = np.arange(len(detections)) if used is None else np.flatnonzero(used)
    world_T_phone = session.world_T_phone[detections.pose_index[rows]]
    world_p_phone = world_T_phone[:, :3, 3]
    world_v_tag = np.einsum(
        "nij,nj->ni", world_T_phone[:, :3, :3], detections.phone_T_tag[rows, :3, 3]
    )
    times = detections.timestamp_s[rows]
    tag_ids = detections.tag_id[rows]
    numerator = denominator = 0.0
    for tag_id in np.unique(tag_ids):
        k = np.flatnonzero(tag_ids == tag_id)
        if k.size < 2:
            continue
        i, j = np.triu_indices(k.size, 1)
        close = np.abs(times[k[j]] - times[k[i]]) <= SCALE_PAIR_WINDOW_S
        d_phone = world_p_phone[k[j[close]]] - world_p_phone[k[i[close]]]
        d_tag = world_v_tag[k[j[close]]] - world_v_tag[k[i[close]]]
        numerator -= float(np.sum(d_phone * d_tag))
        denominator += float(np.sum(d_tag * d_tag))
    return (numerator / denominator if denominator > 0 else 1.0), denominator


def scaled_tag_depths(session: Session, scale: float) -> Session:
    """``session`` with every camera-to-tag translation multiplied by ``scale``."""
    if scale == 1.0:
        return session
    detections = session.detections
    camera_T_tag = detections.camera_T_tag.copy()
    phone_T_tag = detections.phone_T_tag.copy()
    camera_T_tag[:, :3, 3] *= scale
    phone_T_tag[:, :3, 3] *= scale
    return dataclasses.replace(
        session,
        detections=dataclasses.replace(
            detections, camera_T_tag=camera_T_tag, phone_T_tag=phone_T_tag
        ),
    )


def keep_poses(session: Session, keep: BoolArray) -> Session:
    """``session`` with only the poses ``keep`` ((N,) bool) marks, and the detections and points
    of interest on them (a floor of a walk: straight_209_occam's floor 2). Timestamps are kept,
    so the odometry between the poses either side of a gap is their raw relative pose, held as
    loosely as the time across the gap asks."""
    keep = np.asarray(keep, dtype=bool)
    if keep.shape != (session.num_poses,):
        raise ValueError(f"keep must have shape ({session.num_poses},), got {keep.shape}")
    new_row = np.cumsum(keep) - 1
    detections = session.detections
    rows = keep[detections.pose_index]
    columns = {f.name: getattr(detections, f.name)[rows] for f in dataclasses.fields(TagDetections)}
    columns["pose_index"] = new_row[detections.pose_index[rows]].astype(np.int64)
    return dataclasses.replace(
        session,
        pose_id=session.pose_id[keep],
        timestamp_s=session.timestamp_s[keep],
        world_T_phone=session.world_T_phone[keep],
        detections=TagDetections(**columns),
        pois=tuple(
            dataclasses.replace(poi, pose_index=int(new_row[poi.pose_index]))
            for poi in session.pois
            if keep[poi.pose_index]
        ),
    )


def sighting_burst_sizes(session: Session, used: BoolArray) -> FloatArray:
    """(M,) the size of each used detection's burst of sightings (``screening``'s, for a whole
    session)."""
    return _burst_sizes(session.detections, used)


def fit_walk(
    dataset: str, session: Session, screening: Screening, params: SlamParams, depth_scale: float
) -> WalkFit:
    """Step 1: ``session`` (depths scaled already) optimized alone, its noise estimated."""
    started = time.perf_counter()
    inputs = GraphInputs(session, params, screening=screening)
    prepared = time.perf_counter()
    solution = solve(inputs, params)
    optimized = time.perf_counter()
    alone = map_result(
        inputs,
        params,
        solution,
        build_ms=(prepared - started) * 1e3,
        optimize_ms=(optimized - prepared) * 1e3,
    )
    return WalkFit(
        dataset=dataset,
        alone=alone,
        noise=alone.noise,
        noise_scales=inputs.noise_scales[0].copy(),
        cost=float(chain_costs(inputs, params, solution.values)[0]),
        tag_depth_scale=depth_scale,
    )
