"""The graph's inputs (step 1 and 3 of ``slam``): what the factor graph is built from that no
noise parameter changes (:class:`GraphInputs`: the screened detections, the keyframes, the
odometry and up vectors between them, the initial values), and the values keyed as the graph keys
them (:func:`values_from`, :func:`solved_poses`)."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X

from app.domain.frames import FloatArray, se3_inverse
from app.domain.mapping.keyframes import select_keyframes
from app.domain.mapping.noise import COMPONENTS
from app.domain.mapping.params import SlamParams
from app.domain.mapping.screening import Screening, burst_variance_scale, screen_detections
from app.domain.upload.session import IntArray, Session, TagDetections

#: Shortest time credited to an odometry step, s (repeated timestamps would give zero noise).
MIN_ODOMETRY_DT_S = 1e-3
#: The map's up direction, in the world frame (y up).
WORLD_UP = np.array([0.0, 1.0, 0.0])


def to_pose3(T: FloatArray) -> gtsam.Pose3:
    return gtsam.Pose3(T)


def local_landmark_key(index: int) -> int:
    """The graph key of the ``index``-th landmark that is not a tag of the map (``GraphInputs``'
    ``local_landmarks``)."""
    return int(gtsam.symbol("m", index))


def values_from(
    inputs: GraphInputs,
    world_T_keyframe: FloatArray,
    world_T_tag: Mapping[int, FloatArray],
    world_T_local: Mapping[int, FloatArray] | None = None,
) -> gtsam.Values:
    """Start values for ``inputs``' graph: the keyframes from ``world_T_keyframe`` ((K, 4, 4), in
    ``inputs.keyframes`` order), each tag from ``world_T_tag`` (else its initial value), each
    landmark of its own from ``world_T_local`` by key (else its initial value): a warm start."""
    values = gtsam.Values()
    for i, pose in zip(inputs.keyframes.tolist(), world_T_keyframe, strict=True):
        values.insert(X(i), to_pose3(pose))
    for key in landmark_keys_of(inputs):
        symbol = gtsam.Symbol(key)
        if symbol.chr() == ord("l") and int(symbol.index()) in world_T_tag:
            values.insert(key, to_pose3(world_T_tag[int(symbol.index())]))
        elif world_T_local is not None and key in world_T_local:
            values.insert(key, to_pose3(world_T_local[key]))
        else:
            values.insert(key, inputs.initial.atPose3(key))
    return values


def solved_poses(
    inputs: GraphInputs, values: gtsam.Values
) -> tuple[FloatArray, dict[int, FloatArray], dict[int, FloatArray]]:
    """``values`` as arrays: the keyframes' poses ((K, 4, 4)), the tags' by id, and the other
    landmarks' by graph key (the inverse of :func:`values_from`)."""
    world_T_keyframe = np.stack([values.atPose3(X(int(i))).matrix() for i in inputs.keyframes])
    world_T_tag = {t: values.atPose3(L(t)).matrix() for t in sorted(inputs.tag_rows)}
    world_T_local = {key: values.atPose3(key).matrix() for key in sorted(inputs.local_rows)}
    return world_T_keyframe, world_T_tag, world_T_local


def landmark_keys_of(inputs: GraphInputs) -> list[int]:
    return [int(L(t)) for t in sorted(inputs.tag_rows)] + sorted(inputs.local_rows)


class GraphInputs:
    """What the factor graph is built from that no noise parameter changes: the screened
    detections, the keyframes (the phone poses in the graph: ``params.keyframe_interval_s``),
    the odometry between consecutive keyframes, their measured up vectors, the tag measurements
    and the initial values; and each pose chain's (walk's) noise scales (``noise_scales``). A
    sweep prepares them once (:func:`prepare_graph_inputs`) and builds a graph per trial. Phone
    pose ``i`` of the session is the variable ``X(i)``.
    """

    def __init__(
        self,
        session: Session,
        params: SlamParams,
        initial_world_T_phone: FloatArray | None = None,
        *,
        screening: Screening | None = None,
        chain_starts: Sequence[int] = (0,),
        local_landmarks: Mapping[int, int] | None = None,
        tag_variance_scale: FloatArray | None = None,
        odometry_variance_scale: FloatArray | None = None,
        noise_scales: FloatArray | None = None,
        odometry_added_variance: FloatArray | None = None,
    ) -> None:
        """``chain_starts``: the first pose row of each pose chain (a joint map's sessions,
        ``joint.py``): no odometry links the last pose of one chain to the first of the next, and
        both are keyframes; keyframes are chosen in each chain on its own. ``screening``:
        computed by the caller (per session, for a joint map). ``local_landmarks``: detection row
        → a landmark key other than ``L(tag_id)`` (a session's sightings of a shared tag that
        disagree with the others'); those landmarks are solved but are not tags of the map.
        ``tag_variance_scale`` ((M,) per detection; default: each chain's bursts of sightings,
        ``screening.burst_variance_scale``) and ``odometry_variance_scale`` ((N,) per pose, taken
        at the step's first keyframe) multiply the noise variances. ``noise_scales``: (S, 4)
        per chain, the factors on its odometry linear, odometry angular, tag position and tag
        orientation variances (``noise.COMPONENTS``; what each walk's data support).
        ``odometry_added_variance``: (N, 2) variance added to the odometry from pose i to pose
        i + 1, translation (m², per axis) and rotation (rad², per axis), on top of the rate ×
        time and not scaled by ``noise_scales``; a step between keyframes adds up its poses'
        (a building map's stairs, ``joint/stairs.py``)."""
        self.session = session
        self.screening = screening or screen_detections(session.detections, params)
        detections = session.detections
        world_T_phone = session.world_T_phone
        start_T_phone = world_T_phone if initial_world_T_phone is None else initial_world_T_phone
        n = session.num_poses
        starts = sorted({int(s) for s in chain_starts} | {0})
        #: (S,) first pose row of each pose chain
        self.chain_starts = np.array(starts, dtype=np.int64)
        ends = [*starts[1:], n]
        used_poses = detections.pose_index[self.screening.used]
        keyframes: list[int] = []
        keyframe_chain: list[int] = []
        #: (N,) for each pose, the keyframe row its gravity is folded into and the time to it, s
        self.gravity_keyframe = np.zeros(n, dtype=np.int64)
        self.gravity_offset_s = np.zeros(n)
        #: (N,) the chain each pose belongs to
        self.pose_chain = np.zeros(n, dtype=np.int64)
        for c, (a, b) in enumerate(zip(starts, ends, strict=True)):
            times = session.timestamp_s[a:b]
            chosen = select_keyframes(
                times,
                required=used_poses[(used_poses >= a) & (used_poses < b)] - a,
                interval_s=params.keyframe_interval_s,
            )
            nearest = _nearest_keyframe(times, chosen)
            self.gravity_keyframe[a:b] = len(keyframes) + nearest
            self.gravity_offset_s[a:b] = np.abs(times - times[chosen[nearest]])
            self.pose_chain[a:b] = c
            keyframes.extend((chosen + a).tolist())
            keyframe_chain.extend([c] * len(chosen))
        #: (K,) the session's pose indices in the graph, sorted; (K,) the chain of each
        self.keyframes = np.array(keyframes, dtype=np.int64)
        self.keyframe_chain = np.array(keyframe_chain, dtype=np.int64)
        self.gauge_pose = to_pose3(world_T_phone[0])
        #: the first pose's up direction in its phone frame (the gauge leaves its tilt free)
        self.gauge_up = world_T_phone[0, :3, :3].T @ WORLD_UP
        first_of_chain = set(starts)
        #: (K−1,) whether consecutive keyframes k, k+1 are joined by odometry (same chain)
        self.odometry_linked = np.array(
            [b not in first_of_chain for b in keyframes[1:]], dtype=bool
        )
        self.odometry_dt_s = np.round(
            np.maximum(np.diff(session.timestamp_s[self.keyframes]), MIN_ODOMETRY_DT_S), 4
        )
        phone_T_next = (
            se3_inverse(world_T_phone[self.keyframes[:-1]]) @ (world_T_phone[self.keyframes[1:]])
        )
        self.phone_T_next = [to_pose3(T) for T in phone_T_next]
        #: (K, 3) each keyframe's measured up direction, phone frame
        self.phone_up_xyz = np.einsum("nji,j->ni", world_T_phone[self.keyframes, :3, :3], WORLD_UP)
        self.phone_up = [gtsam.Unit3(up) for up in self.phone_up_xyz]
        self.tag_detection_rows = [int(row) for row in np.flatnonzero(self.screening.used)]
        self.tag_ids = [int(detections.tag_id[row]) for row in self.tag_detection_rows]
        local = dict(local_landmarks or {})
        #: the landmark key each used detection's factor connects to
        self.landmark_keys = [
            local.get(row, L(tag_id))
            for row, tag_id in zip(self.tag_detection_rows, self.tag_ids, strict=True)
        ]
        self.tag_pose_indices = [int(detections.pose_index[row]) for row in self.tag_detection_rows]
        #: (U,) the chain each used detection belongs to
        self.detection_chain = self.pose_chain[np.array(self.tag_pose_indices, dtype=np.int64)]
        self.phone_T_tag = [
            to_pose3(detections.phone_T_tag[row]) for row in self.tag_detection_rows
        ]
        self.camera_T_tag = detections.camera_T_tag[self.tag_detection_rows]
        if tag_variance_scale is None:  # each chain's bursts of sightings (screening.py)
            tag_variance_scale = np.ones(len(detections))
            for a, b in zip(starts, ends, strict=True):
                chain_rows = np.flatnonzero(
                    (detections.pose_index >= a) & (detections.pose_index < b)
                )
                tag_variance_scale[chain_rows] = burst_variance_scale(
                    _detection_rows(detections, chain_rows), self.screening.used[chain_rows]
                )
        #: (U,) and (K−1,) variance multipliers of the tag and odometry factors
        self.tag_variance_scale = np.asarray(tag_variance_scale, dtype=np.float64)[
            self.tag_detection_rows
        ]
        self.odometry_variance_scale = (
            np.ones(len(keyframes) - 1 if keyframes else 0)
            if odometry_variance_scale is None
            else np.asarray(odometry_variance_scale, dtype=np.float64)[self.keyframes[:-1]]
        )
        #: (K−1, 2) variance added to each odometry step, translation m² and rotation rad²
        self.odometry_added_variance = np.zeros((max(len(keyframes) - 1, 0), 2))
        if odometry_added_variance is not None:
            added = np.asarray(odometry_added_variance, dtype=np.float64).reshape(n, 2)
            summed = np.concatenate([np.zeros((1, 2)), np.cumsum(added, axis=0)])
            self.odometry_added_variance = summed[self.keyframes[1:]] - summed[self.keyframes[:-1]]
        #: (S, 4) each chain's factors on its noise components (``noise.COMPONENTS``)
        self.noise_scales = (
            np.ones((len(starts), len(COMPONENTS)))
            if noise_scales is None
            else np.array(noise_scales, dtype=np.float64).reshape(len(starts), len(COMPONENTS))
        )
        self.initial = gtsam.Values()
        for i in keyframes:
            self.initial.insert(X(i), to_pose3(start_T_phone[i]))
        self.tag_rows: dict[int, list[int]] = {}
        #: rows of the detections of each local landmark, by key
        self.local_rows: dict[int, list[int]] = {}
        for row, tag_id, pose_index, key in zip(
            self.tag_detection_rows,
            self.tag_ids,
            self.tag_pose_indices,
            self.landmark_keys,
            strict=True,
        ):
            rows = self.tag_rows if key == L(tag_id) else self.local_rows
            label = tag_id if key == L(tag_id) else key
            if label not in rows:
                rows[label] = []
                first_T_tag = start_T_phone[pose_index] @ detections.phone_T_tag[row]
                self.initial.insert(key, to_pose3(first_T_tag))
            rows[label].append(row)

    @property
    def num_chains(self) -> int:
        return int(self.chain_starts.shape[0])

    def odometry_scales(self) -> tuple[FloatArray, FloatArray]:
        """(K−1,) the linear and the angular variance factor of each odometry step."""
        chain = self.keyframe_chain[:-1]
        legacy = self.odometry_variance_scale
        return legacy * self.noise_scales[chain, 0], legacy * self.noise_scales[chain, 1]

    def tag_scales(self) -> tuple[FloatArray, FloatArray]:
        """(U,) the position and the orientation variance factor of each tag factor."""
        chain = self.detection_chain
        burst = self.tag_variance_scale
        return burst * self.noise_scales[chain, 2], burst * self.noise_scales[chain, 3]


def _detection_rows(detections: TagDetections, rows: IntArray) -> TagDetections:
    """The detections ``rows`` of ``detections``, as a ``TagDetections`` of their own."""
    return TagDetections(
        **{f.name: getattr(detections, f.name)[rows] for f in dataclasses.fields(TagDetections)}
    )


def _nearest_keyframe(times_s: FloatArray, keyframes: IntArray) -> IntArray:
    """(n,) for each pose of a chain, the row in ``keyframes`` of the keyframe nearest in time
    (the earlier on a tie; a keyframe is its own)."""
    key_times = times_s[keyframes]
    after = np.clip(np.searchsorted(key_times, times_s, side="left"), 0, len(keyframes) - 1)
    before = np.clip(after - 1, 0, len(keyframes) - 1)
    earlier = np.abs(times_s - key_times[before]) <= np.abs(key_times[after] - times_s)
    nearest = np.where(earlier, before, after)
    nearest[keyframes] = np.arange(len(keyframes))
    return np.asarray(nearest, dtype=np.int64)


def prepare_graph_inputs(session: Session, params: SlamParams | None = None) -> GraphInputs:
    """Screen ``session`` with ``params``' rejection thresholds and precompute the graph's
    measurements, for :func:`optimize_tag_poses` with many noise parameters."""
    return GraphInputs(session, params or SlamParams())
