"""Keyframes (``app/domain/mapping/keyframes.py``): which poses the graph holds, how the others are
placed, and that a map with keyframes is the map with every pose on real sessions."""

from __future__ import annotations

import dataclasses
import itertools
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from app.domain.evaluation.ground_truth import load_ground_truth
from app.domain.evaluation.metrics import ground_truth_metric, tag_rmse_m, umeyama_rigid
from app.domain.frames import make_pose, rotation_about_y, so3_exp, so3_log
from app.domain.mapping.keyframes import interpolate_poses, select_keyframes
from app.domain.mapping.params import SlamParams
from app.domain.mapping.slam import optimize_session
from app.domain.upload.session import load_session

DATA = Path(__file__).parents[2] / "data"


# --------------------------------------------------------------------------- selection


@given(
    steps_s=st.lists(st.floats(0.0, 3.0), min_size=1, max_size=60),
    interval_s=st.floats(0.1, 5.0),
    required=st.sets(st.integers(0, 60), max_size=10),
)
def test_keyframes_keep_the_ends_the_required_and_gaps_within_the_interval(
    steps_s: list[float], interval_s: float, required: set[int]
) -> None:
    timestamp_s = np.concatenate([[0.0], np.cumsum(steps_s)])
    n = timestamp_s.size
    required_poses = sorted(i for i in required if i < n)

    keyframes = select_keyframes(timestamp_s, required=required_poses, interval_s=interval_s)

    assert keyframes[0] == 0
    assert keyframes[-1] == n - 1
    assert np.all(np.diff(keyframes) > 0)
    assert set(required_poses) <= set(keyframes.tolist())
    for a, b in itertools.pairwise(keyframes):
        gap_s = timestamp_s[b] - timestamp_s[a]
        # a gap wider than the interval is a single step (nothing in between to keep)
        assert gap_s <= interval_s + 1e-12 or b == a + 1


def test_keyframes_at_a_steady_rate_leave_out_what_the_interval_allows() -> None:
    timestamp_s = np.arange(21) * 0.5  # 10 s at 2 Hz
    keyframes = select_keyframes(timestamp_s, required=[7], interval_s=2.0)
    assert keyframes.tolist() == [0, 4, 7, 11, 15, 19, 20]
    every = select_keyframes(timestamp_s, required=[], interval_s=0.0)
    assert every.tolist() == list(range(21))
    assert select_keyframes(np.empty(0), required=[], interval_s=2.0).size == 0


# --------------------------------------------------------------------------- interpolation


def walk(n: int = 11) -> tuple[np.ndarray, np.ndarray]:
    """A raw trajectory turning as it goes, 1 s apart."""
    timestamp_s = np.arange(n, dtype=float)
    raw = np.stack(
        [make_pose(rotation_about_y(0.2 * i), [1.5 * i, 0.1 * i, -0.3 * i]) for i in range(n)]
    )
    return timestamp_s, raw


def test_a_correction_that_grows_linearly_in_time_is_recovered_at_every_pose() -> None:
    """The correction turns about y and shifts at a constant rate: interpolating it between
    keyframes reproduces it exactly at the poses in between."""
    timestamp_s, raw = walk()
    corrections = np.stack(
        [make_pose(rotation_about_y(0.03 * t), [0.1 * t, -0.02 * t, 0.05 * t]) for t in timestamp_s]
    )
    truth = corrections @ raw
    keyframes = np.array([0, 3, 4, 10])

    placed = interpolate_poses(raw, timestamp_s, keyframes, truth[keyframes])

    np.testing.assert_allclose(placed, truth, atol=1e-12)
    np.testing.assert_array_equal(placed[keyframes], truth[keyframes])


def test_with_every_pose_a_keyframe_the_optimized_poses_are_returned_as_they_are() -> None:
    timestamp_s, raw = walk()
    optimized = raw + 1e-3
    placed = interpolate_poses(raw, timestamp_s, np.arange(raw.shape[0]), optimized)
    np.testing.assert_array_equal(placed, optimized)


def test_poses_with_one_timestamp_are_placed_by_their_index() -> None:
    timestamp_s, raw = walk(5)
    timestamp_s[:] = 0.0
    shifted = make_pose(np.eye(3), [0.0, 0.0, 4.0]) @ raw[4]
    placed = interpolate_poses(raw, timestamp_s, np.array([0, 4]), np.stack([raw[0], shifted]))
    np.testing.assert_allclose(placed[2, :3, 3] - raw[2, :3, 3], [0.0, 0.0, 2.0], atol=1e-12)


@settings(max_examples=300)
@given(
    axis=st.tuples(*[st.floats(-1.0, 1.0)] * 3).filter(lambda v: np.linalg.norm(v) > 1e-3),
    angle_rad=st.one_of(
        st.floats(0.0, np.pi), st.floats(np.pi - 1e-3, np.pi), st.floats(0.0, 1e-7)
    ),
)
def test_so3_log_inverts_so3_exp(axis: tuple[float, float, float], angle_rad: float) -> None:
    rotation_vector = np.asarray(axis) / np.linalg.norm(axis) * angle_rad
    R = so3_exp(rotation_vector)
    np.testing.assert_allclose(so3_exp(so3_log(R)), R, atol=1e-7)
    if angle_rad < np.pi - 1e-3:
        np.testing.assert_allclose(so3_log(R), rotation_vector, atol=1e-9)


# --------------------------------------------------------------------------- real sessions


@pytest.mark.parametrize(
    "name", ["occam_room", "floor_2_straight", "straight_209_occam", "desnat_straight_once"]
)
def test_a_keyframe_map_is_the_map_with_every_pose(name: str) -> None:
    """At the default 2 s between keyframes, on every real session with ground truth, after a
    rigid alignment: with the same noise, tags within 1.5 cm RMS of the every-pose map's, every
    pose within 3 cm, the ground-truth metric within 1%; and the graph holds at most 60% of the
    poses. With the noise estimated from each graph's own residuals (the default), the estimates
    agree (the poses between keyframes fold their gravity into the keyframes' factors, so
    gravity weighs the same in both: measured ratios 0.99–1.06 for three components, 0.56–0.97
    for the odometry's yaw, the least determined) and so do the tags (measured 0.3–17.5 mm)."""
    session = load_session(DATA / "sessions" / f"{name}.json")
    ground_truth_file = "occam_room_tape.json" if name == "occam_room" else "rtabmap_mac_1_2.txt"
    truth = load_ground_truth(DATA / "ground_truth" / ground_truth_file)
    given = SlamParams(estimate_noise=False)
    every_pose = optimize_session(session, dataclasses.replace(given, keyframe_interval_s=0.0))
    keyframes = optimize_session(session, given)

    assert keyframes.residuals.keyframe_index.size <= 0.6 * session.num_poses
    assert every_pose.residuals.keyframe_index.size == session.num_poses
    np.testing.assert_array_equal(keyframes.tag_ids, every_pose.tag_ids)
    assert tag_rmse_m(keyframes.tag_poses(), every_pose.tag_poses()) < 0.015
    every_xyz = every_pose.world_T_phone[:, :3, 3]
    keyframe_xyz = keyframes.world_T_phone[:, :3, 3]
    every_T_keyframe = umeyama_rigid(keyframe_xyz, every_xyz)
    aligned_xyz = keyframe_xyz @ every_T_keyframe[:3, :3].T + every_T_keyframe[:3, 3]
    assert np.linalg.norm(aligned_xyz - every_xyz, axis=1).max() < 0.03
    assert ground_truth_metric(keyframes.tag_poses(), truth) == pytest.approx(
        ground_truth_metric(every_pose.tag_poses(), truth), rel=0.01
    )

    estimated_every = optimize_session(session, SlamParams(keyframe_interval_s=0.0))
    estimated = optimize_session(session, SlamParams())
    assert estimated.noise is not None
    assert estimated_every.noise is not None
    ratio = estimated.noise.scales / estimated_every.noise.scales
    assert np.all((ratio > 0.5) & (ratio < 2.0)), ratio
    assert tag_rmse_m(estimated.tag_poses(), estimated_every.tag_poses()) < 0.02
