"""Live localization against a fixed map (architecture §6): convergence, warm start, the JSON state,
bounded cost, validation that leaves the state alone, and the real cross-session replay."""

from __future__ import annotations

import copy
import dataclasses
import json
import math
from pathlib import Path
from typing import Any

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import X

from app.domain.errors import InvisibleMapError, ParameterError
from app.domain.evaluation.simulate import SimulationConfig, simulate_session
from app.domain.frames import make_pose, rotation_about_y, rotation_angle_rad, se3_inverse
from app.domain.localize import (
    LocalizationUpdateError,
    LocalizerParams,
    LocalizerState,
    LocalizerStateError,
    median_and_p90,
    parse_update,
    prediction_errors_m,
    replay_session,
    session_update_documents,
    update,
)
from app.domain.mapping.screening import project_tag_corners, screen_detections
from app.domain.mapping.slam import (
    WORLD_UP,
    odometry_sigmas,
    optimize_session,
    tag_covariance_in_tag_frame,
    to_pose3,
)
from app.domain.upload.session import Session, load_session, parse_session

SESSIONS = Path(__file__).parents[2] / "data" / "sessions"

#: The navigation session's frame in the map: turned 2 rad about gravity and moved.
MAP_T_SESSION_TRUE = make_pose(rotation_about_y(2.0), [12.0, -0.4, -21.0])


# --------------------------------------------------------------------------- builders


def in_session_frame(session: Session, map_T_session: np.ndarray) -> Session:
    """``session`` with its odometry in a frame placed at ``map_T_session`` in the map."""
    return dataclasses.replace(
        session, world_T_phone=se3_inverse(map_T_session) @ session.world_T_phone
    )


@pytest.fixture(scope="module")
def walk():
    """A simulated walk (the truth's frame is the map's), its tags as the map, and the session
    expressed in a frame away from the map's."""
    sim = simulate_session(SimulationConfig(num_poses=1_200, seed=1))
    session = in_session_frame(parse_session(sim.upload), MAP_T_SESSION_TRUE)
    return sim, session, dict(sim.world_T_tag_true)


@pytest.fixture(scope="module")
def documents(walk):
    _, session, _ = walk
    return session_update_documents(session, 10)


def run(documents: list[dict[str, Any]], map_tags, params: LocalizerParams | None = None):
    """(state, results) after feeding ``documents`` in order."""
    state = LocalizerState.initial()
    results = []
    for document in documents:
        state, result = update(state, parse_update(document), map_tags, params)
        results.append(result)
    return state, results


def first_localized(documents: list[dict[str, Any]], map_tags) -> int:
    """Index of the first document with a usable detection."""
    _, results = run(documents, map_tags)
    return next(i for i, r in enumerate(results) if r.status == "localized")


def localized_state(documents, map_tags, count: int) -> LocalizerState:
    state, _ = run(documents[:count], map_tags)
    assert state.localized
    return state


# --------------------------------------------------------------------------- convergence


def test_not_localized_before_the_first_tag_then_converges_to_the_truth(walk, documents):
    sim, _, map_tags = walk
    state = LocalizerState.initial()
    errors_m, seen_tags = [], set()
    for document in documents:
        batch = parse_update(document)
        had_detection = len(batch.detections) > 0
        state, result = update(state, batch, map_tags)
        if not seen_tags and not had_detection:
            assert result.status == "not_localized"
            assert result.map_T_phone is None
            assert result.map_T_session is None
            assert result.position_sigma_m is None
        seen_tags |= set(result.tags_used)
        if result.status == "localized":
            assert seen_tags
            assert result.map_T_phone is not None
            error_m = np.linalg.norm(
                result.map_T_phone[:3, 3] - sim.world_T_phone_true[result.pose_id][:3, 3]
            )
            if len(seen_tags) >= 3:
                errors_m.append(float(error_m))
    median_m, p90_m = median_and_p90(errors_m)
    assert len(errors_m) > 50
    assert median_m < 0.1
    assert p90_m < 0.2
    answer = json.loads(json.dumps(result.to_json(), allow_nan=False))
    assert answer["status"] == "localized"
    assert len(answer["map_T_phone"]) == 4
    assert answer["pose_id"] == result.pose_id


def test_map_T_session_is_a_yaw_and_a_translation_near_the_truth(walk, documents):
    """Against the true session-to-map transform at the last pose (the odometry has drifted
    since the start, so it is no longer ``MAP_T_SESSION_TRUE``)."""
    sim, session, map_tags = walk
    _, results = run(documents, map_tags)
    result = results[-1]
    assert result.map_T_session is not None
    assert result.covariance is not None
    map_R_session = result.map_T_session[:3, :3]
    tilt_rad = math.acos(min(1.0, float(WORLD_UP @ map_R_session @ WORLD_UP)))
    assert tilt_rad < 0.01  # gravity holds roll and pitch
    map_T_session_true = sim.world_T_phone_true[-1] @ se3_inverse(session.world_T_phone[-1])
    error = se3_inverse(map_T_session_true) @ result.map_T_session
    assert rotation_angle_rad(error[:3, :3]) < 0.01
    # the session's origin is ~25 m away: compare where both put the phone
    phone_error = se3_inverse(session.world_T_phone[-1]) @ error @ session.world_T_phone[-1]
    assert np.linalg.norm(phone_error[:3, 3]) < 0.2
    assert result.covariance.shape == (6, 6)
    assert np.all(np.linalg.eigvalsh(result.covariance) > 0)
    assert result.position_sigma_m is not None
    assert 0.0 < result.position_sigma_m < 1.0


def test_fixed_lag_smoother_matches_the_batch_solution_over_all_poses(walk):
    """The paper's formulation solved over every pose (odometry factor per step, tags fixed) and
    the windowed keyframe chain with its marginalized prior give the same latest pose."""
    _, session_full, map_tags = walk
    n = 400
    session = dataclasses.replace(
        session_full,
        pose_id=session_full.pose_id[:n],
        timestamp_s=session_full.timestamp_s[:n],
        world_T_phone=session_full.world_T_phone[:n],
        detections=_detections_before(session_full, n),
    )
    params = LocalizerParams(keyframe_merge_s=0.0, window_keyframes=2)
    steps = replay_session(map_tags, session, 10, params)
    ours = steps[-1].result
    assert ours.map_T_phone is not None
    assert ours.position_sigma_m is not None
    assert max(s.result.window_keyframes for s in steps) <= 2

    batch_T, batch_sigma_m = _batch_solution(session, map_tags, params)
    assert np.linalg.norm(batch_T[:3, 3] - ours.map_T_phone[:3, 3]) < 1e-3
    assert ours.position_sigma_m == pytest.approx(batch_sigma_m, rel=1e-3)


def _detections_before(session: Session, n: int):
    keep = session.detections.pose_index < n
    return type(session.detections)(
        **{
            f.name: getattr(session.detections, f.name)[keep]
            for f in dataclasses.fields(session.detections)
        }
    )


def _batch_solution(session: Session, map_tags, params: LocalizerParams):
    """Latest ``map_T_phone`` and its position σ from one LM over all poses since the first
    detection: odometry per step (``odometry_sigmas``), gravity at the detection poses, each tag
    factor ``BetweenFactorPose3(X, tag)`` with the tag held at the map's pose."""
    slam = params.slam
    used = screen_detections(session.detections, slam).used
    rows = np.flatnonzero(used)
    detection_poses = {int(session.detections.pose_index[r]) for r in rows}
    first = min(detection_poses)
    P = session.world_T_phone
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    gravity = gtsam.noiseModel.Isotropic.Sigma(2, math.sqrt(slam.gravity_var_rad2))
    huber = gtsam.noiseModel.mEstimator.Huber.Create(params.huber_k)
    map_covariance = np.diag(
        [params.map_tag_orientation_var_rad2] * 3 + [params.map_tag_position_var_m2] * 3
    )
    for i in range(first, session.num_poses):
        values.insert(X(i), to_pose3(MAP_T_SESSION_TRUE @ P[i]))
        if i > first:
            dt_s = float(session.timestamp_s[i] - session.timestamp_s[i - 1])
            graph.add(
                gtsam.BetweenFactorPose3(
                    X(i - 1),
                    X(i),
                    to_pose3(se3_inverse(P[i - 1]) @ P[i]),
                    gtsam.noiseModel.Diagonal.Sigmas(odometry_sigmas(dt_s, slam)),
                )
            )
        if i in detection_poses:
            phone_up = P[i][:3, :3].T @ WORLD_UP
            graph.add(
                gtsam.AttitudeFactorPose3(
                    X(i), gtsam.Unit3(WORLD_UP), gravity, gtsam.Unit3(phone_up)
                )
            )
    for row in rows:
        i = int(session.detections.pose_index[row])
        tag_id = int(session.detections.tag_id[row])
        covariance = (
            tag_covariance_in_tag_frame(session.detections.camera_T_tag[row], slam) + map_covariance
        )
        tag = gtsam.Symbol("t", tag_id).key()
        if not values.exists(tag):
            values.insert(tag, to_pose3(map_tags[tag_id]))
            graph.add(gtsam.NonlinearEqualityPose3(tag, to_pose3(map_tags[tag_id])))
        graph.add(
            gtsam.BetweenFactorPose3(
                X(i),
                tag,
                to_pose3(session.detections.phone_T_tag[row]),
                gtsam.noiseModel.Robust.Create(
                    huber, gtsam.noiseModel.Gaussian.Covariance(covariance)
                ),
            )
        )
    solved = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
    last = session.num_poses - 1
    map_T_phone = solved.atPose3(X(last)).matrix()
    covariance = gtsam.Marginals(graph, solved).marginalCovariance(X(last))
    return map_T_phone, math.sqrt(float(np.trace(covariance[3:, 3:])))


# --------------------------------------------------------------------------- warm start, state


def test_an_update_without_tags_keeps_the_estimate_and_follows_the_odometry(walk, documents):
    _, _, map_tags = walk
    start = first_localized(documents, map_tags)
    state = localized_state(documents, map_tags, start + 3)
    before = state.map_T_session()
    sigma_before = state.map_T_session_covariance()
    batch = parse_update({"poses": documents[start + 3]["poses"], "tag_data": []})
    new_state, result = update(state, batch, map_tags)
    assert result.status == "localized"
    assert result.iterations == 0
    assert result.tags_used == ()
    np.testing.assert_allclose(result.map_T_session, before, atol=1e-12)
    np.testing.assert_allclose(result.map_T_phone, before @ batch.session_T_phone[-1], atol=1e-12)
    assert result.pose_id == int(batch.pose_id[-1])
    # the session frame's uncertainty grows with the odometry walked
    assert sigma_before is not None
    assert result.covariance is not None
    assert np.all(np.linalg.eigvalsh(result.covariance - sigma_before) > -1e-15)
    assert np.trace(result.covariance) > np.trace(sigma_before)
    assert all(
        np.array_equal(a.map_T_phone, b.map_T_phone)
        for a, b in zip(new_state.keyframes, state.keyframes, strict=True)
    )


def test_state_json_round_trip_gives_identical_results(walk, documents):
    _, _, map_tags = walk
    start = first_localized(documents, map_tags)
    state = localized_state(documents, map_tags, start + 40)
    assert state.prior_map_T_phone is not None  # the window has marginalized something
    stored = json.loads(json.dumps(state.to_json(), allow_nan=False))
    restored = LocalizerState.from_json(stored)
    assert restored.to_json() == state.to_json()
    for document in documents[start + 40 : start + 50]:
        batch = parse_update(document)
        state, expected = update(state, batch, map_tags)
        restored = LocalizerState.from_json(json.loads(json.dumps(restored.to_json())))
        restored, got = update(restored, batch, map_tags)
        assert got.status == expected.status
        assert np.array_equal(got.map_T_phone, expected.map_T_phone)
        assert np.array_equal(got.covariance, expected.covariance)
        assert got.tags_used == expected.tags_used
    assert restored.to_json() == state.to_json()


def test_unreadable_state_raises_a_state_error():
    good = LocalizerState.initial().to_json()
    with pytest.raises(LocalizerStateError):
        LocalizerState.from_json({**good, "version": 99})
    broken = copy.deepcopy(good)
    broken["recent_poses"]["session_T_phone"] = "not base64!"
    with pytest.raises(LocalizerStateError):
        LocalizerState.from_json(broken)
    with pytest.raises(LocalizerStateError):
        LocalizerState.from_json({"version": 1})


def test_update_cost_is_bounded_by_the_window(walk, documents):
    """Flat cost: the window, the detections in it and the stored poses stay bounded however
    long the session (timing is the benchmark's job)."""
    _, _, map_tags = walk
    params = LocalizerParams(window_keyframes=4, max_detections_per_keyframe=3, recent_poses=12)
    state = LocalizerState.initial()
    sizes = []
    for document in documents:
        state, result = update(state, parse_update(document), map_tags, params)
        assert result.window_keyframes <= params.window_keyframes
        assert sum(len(k.detections) for k in state.keyframes) <= 4 * 3
        assert state.recent_pose_id.size <= params.recent_poses
        sizes.append(len(json.dumps(state.to_json())))
    assert state.num_keyframes_marginalized > 20
    assert state.num_poses == 1_200
    quarter = len(sizes) // 4
    assert max(sizes[quarter:]) <= 1.5 * max(sizes[:quarter])


def test_a_late_detection_on_an_earlier_batchs_pose_splits_the_odometry_chain(walk, documents):
    """A detection sent one batch late lands where it was made: same answer as on time."""
    _, _, map_tags = walk
    start = first_localized(documents, map_tags)
    k = next(i for i in range(start + 5, len(documents)) if documents[i]["tag_data"])
    on_time = localized_state(documents, map_tags, k + 2)
    late_docs = copy.deepcopy(documents[: k + 2])
    late_docs[k + 1]["tag_data"] = late_docs[k]["tag_data"] + late_docs[k + 1]["tag_data"]
    late_docs[k]["tag_data"] = []
    late = localized_state(late_docs, map_tags, k + 2)
    on_time_T, late_T = on_time.map_T_session(), late.map_T_session()
    assert on_time_T is not None
    assert late_T is not None
    assert np.linalg.norm(on_time_T[:3, 3] - late_T[:3, 3]) < 1e-4
    assert [kf.pose_id for kf in late.keyframes] == [kf.pose_id for kf in on_time.keyframes]


def test_a_late_detection_before_the_marginalized_window_is_rejected_not_an_error(walk, documents):
    _, _, map_tags = walk
    params = LocalizerParams(
        window_keyframes=2, keyframe_merge_s=0.0, max_detections_per_keyframe=1
    )
    state = LocalizerState.initial()
    for k, document in enumerate(documents):
        state, _ = update(state, parse_update(document), map_tags, params)
        if (
            state.prior_map_T_phone is not None
            and state.keyframes[0].pose_id > state.recent_pose_id[0]
            and documents[k + 1]["tag_data"]
        ):
            break
    late = copy.deepcopy(documents[k + 1])
    late["tag_data"] = late["tag_data"][:1]
    late["tag_data"][0][0]["pose_id"] = int(state.recent_pose_id[0])
    before = copy.deepcopy(state.to_json())
    _, result = update(state, parse_update(late), map_tags, params)
    assert [r.reason for r in result.rejections] == ["before_window"]
    assert result.detections_used == 0
    assert state.to_json() == before


def test_out_of_range_parameters_are_refused():
    with pytest.raises(ParameterError):
        LocalizerParams(window_keyframes=1)
    with pytest.raises(ParameterError):
        LocalizerParams(huber_k=math.nan)


def test_a_consistent_outlier_is_held_back_by_the_robust_kernel(walk, documents):
    """A tag pose 1 m off whose corners agree with it passes the screen; Huber limits its pull."""
    _, _, map_tags = walk
    start = first_localized(documents, map_tags)
    k = next(i for i in range(start + 20, len(documents)) if documents[i]["tag_data"])
    state = localized_state(documents, map_tags, k)
    _, clean = update(state, parse_update(documents[k]), map_tags)
    bad = copy.deepcopy(documents[k])
    detection = bad["tag_data"][0][0]
    camera_T_tag = np.array(detection["tag_pose"]).reshape(4, 4)
    camera_T_tag[:3, 3] += [0.6, 0.0, 0.8]
    detection["tag_pose"] = camera_T_tag.reshape(16).tolist()
    batch = parse_update(bad)
    corners = project_tag_corners(batch.detections, np.full(len(batch.detections), 0.173))
    detection["tag_corners_pixel_coordinates"] = corners[0].reshape(8).tolist()
    _, corrupted = update(state, parse_update(bad), map_tags)
    assert corrupted.rejections == ()
    assert clean.map_T_phone is not None
    assert corrupted.map_T_phone is not None
    assert np.linalg.norm(corrupted.map_T_phone[:3, 3] - clean.map_T_phone[:3, 3]) < 0.25


def test_screened_detections_are_reported_not_used(walk, documents):
    _, _, map_tags = walk
    start = first_localized(documents, map_tags)
    bad = copy.deepcopy(documents[start])
    for frame in bad["tag_data"]:
        for detection in frame:
            corners = detection["tag_corners_pixel_coordinates"]
            detection["tag_corners_pixel_coordinates"] = [
                v + 40.0 * (j % 3) for j, v in enumerate(corners)
            ]
    state, _ = run(documents[:start], map_tags)
    _, result = update(state, parse_update(bad), map_tags)
    assert result.status == "not_localized"
    assert result.detections_used == 0
    assert {r.reason for r in result.rejections} == {"reprojection"}


# --------------------------------------------------------------------------- validation


def _pose_entry(pose_id: int, timestamp_s: float, T: np.ndarray) -> dict[str, Any]:
    return {"id": pose_id, "timestamp": timestamp_s, "pose": T.T.reshape(16).tolist()}


def _malformed(documents: list[dict[str, Any]], start: int, case: str) -> tuple[dict, str]:
    """A broken copy of ``documents[start]`` and the field its error must name."""
    document = copy.deepcopy(documents[start])
    frame = next((i for i, f in enumerate(documents[start]["tag_data"]) if f), None)
    if case == "unknown_tag":
        assert frame is not None
        document["tag_data"][frame][0]["tag_id"] = 9_999
        return document, f"tag_data[{frame}][0].tag_id"
    if case == "unknown_pose_id":
        assert frame is not None
        document["tag_data"][frame][0]["pose_id"] = 123_456
        return document, f"tag_data[{frame}][0].pose_id"
    if case == "timestamp_backwards":
        document["poses"][0]["timestamp"] = documents[start - 1]["poses"][-1]["timestamp"] - 0.5
        return document, "poses[0].timestamp"
    if case == "timestamp_backwards_in_batch":
        document["poses"][3]["timestamp"] = document["poses"][2]["timestamp"] - 0.01
        return document, "poses[3].timestamp"
    if case == "pose_id_backwards":
        document["poses"][0]["id"] = documents[start - 1]["poses"][-1]["id"]
        return document, "poses[0].id"
    if case == "not_rigid":
        T = np.array(document["poses"][2]["pose"]).reshape(4, 4).T
        T[:3, :3] *= 1.2
        document["poses"][2]["pose"] = T.T.reshape(16).tolist()
        return document, "poses[2].pose"
    if case == "nan_in_pose":
        document["poses"][1]["pose"][13] = math.nan
        return document, "poses[1].pose[13]"
    if case == "nan_in_tag_pose":
        assert frame is not None
        document["tag_data"][frame][0]["tag_pose"][3] = math.inf
        return document, f"tag_data[{frame}][0].tag_pose[3]"
    if case == "short_pose":
        document["poses"][0]["pose"] = document["poses"][0]["pose"][:15]
        return document, "poses[0].pose"
    raise AssertionError(case)


@pytest.mark.parametrize(
    "case",
    [
        "unknown_tag",
        "unknown_pose_id",
        "timestamp_backwards",
        "timestamp_backwards_in_batch",
        "pose_id_backwards",
        "not_rigid",
        "nan_in_pose",
        "nan_in_tag_pose",
        "short_pose",
    ],
)
def test_a_malformed_update_names_the_field_and_leaves_the_state_unchanged(walk, documents, case):
    _, _, map_tags = walk
    start = first_localized(documents, map_tags)
    k = next(i for i in range(start + 3, len(documents)) if documents[i]["tag_data"])
    state = localized_state(documents, map_tags, k)
    before = copy.deepcopy(state.to_json())
    document, field = _malformed(documents, k, case)
    with pytest.raises(LocalizationUpdateError) as caught:
        update(state, parse_update(document), map_tags)
    assert caught.value.field == field
    assert isinstance(caught.value, InvisibleMapError)
    assert field in str(caught.value)
    assert state.to_json() == before
    # and the state still takes the good update
    _, result = update(state, parse_update(documents[k]), map_tags)
    assert result.status == "localized"


def test_unknown_tag_message_lists_the_map(walk, documents):
    _, _, map_tags = walk
    start = first_localized(documents, map_tags)
    document, _ = _malformed(documents, start, "unknown_tag")
    with pytest.raises(LocalizationUpdateError, match="tag 9999 is not in this map"):
        update(LocalizerState.initial(), parse_update(document), map_tags)


@pytest.mark.parametrize(
    ("document", "field"),
    [
        ([], ""),
        ({"poses": {}}, "poses"),
        ({"poses": [{"id": 0, "timestamp": 1.0}]}, "poses[0].pose"),
        ({"poses": [{"id": 0.5, "timestamp": 1.0, "pose": [0] * 16}]}, "poses[0].id"),
        ({"tag_data": [[{"tag_id": -1}]]}, "tag_data[0][0].tag_id"),
        ({"tag_data": [3]}, "tag_data[0]"),
    ],
)
def test_parse_update_names_the_field(document, field):
    with pytest.raises(LocalizationUpdateError) as caught:
        parse_update(document)
    assert caught.value.field == field


def test_parse_update_reads_poses_column_major_and_tags_row_major():
    session_T_phone = make_pose(rotation_about_y(0.4), [1.0, 2.0, 3.0])
    camera_T_tag = make_pose(rotation_about_y(0.1) @ np.diag([1.0, -1.0, -1.0]), [0.1, 0.2, 1.5])
    batch = parse_update(
        {
            "poses": [_pose_entry(7, 10.0, session_T_phone)],
            "tag_data": [
                [
                    {
                        "tag_id": 4,
                        "pose_id": 7,
                        "tag_pose": camera_T_tag.reshape(16).tolist(),
                        "camera_intrinsics": [1000.0, 1000.0, 500.0, 400.0],
                        "tag_corners_pixel_coordinates": [0.0] * 8,
                    }
                ]
            ],
        }
    )
    np.testing.assert_allclose(batch.session_T_phone[0], session_T_phone, atol=1e-12)
    np.testing.assert_allclose(batch.detections.camera_T_tag[0], camera_T_tag, atol=1e-12)
    np.testing.assert_allclose(
        batch.detections.phone_T_tag[0], np.diag([1.0, -1.0, -1.0, 1.0]) @ camera_T_tag
    )
    assert batch.detection_pose_id.tolist() == [7]
    assert batch.detection_field == ("tag_data[0][0]",)


def test_an_empty_update_is_accepted_and_changes_only_the_count():
    state, result = update(LocalizerState.initial(), parse_update({}), {})
    assert result.status == "not_localized"
    assert result.pose_id is None
    assert state.num_updates == 1


# --------------------------------------------------------------------------- real data


@pytest.fixture(scope="module")
def real_replay():
    map_tags = optimize_session(load_session(SESSIONS / "floor_2_straight.json")).tag_poses()
    session = load_session(SESSIONS / "desnat_straight_once.json")
    return replay_session(map_tags, session, 10)


@pytest.mark.slow
def test_real_cross_session_tag_prediction_median_within_the_arrival_radius(real_replay):
    """Map from floor_2_straight, replay desnat_straight_once: at each tag detection, before
    the update that carries it, the tag predicted from the estimate lies within 0.3 m (median)
    of the map's tag; also for the first detection of each new sighting (the next tag)."""
    all_m = prediction_errors_m(real_replay)
    first_m = prediction_errors_m(real_replay, first_of_sighting_only=True)
    assert len(all_m) > 60
    assert len(first_m) == 7  # tags 301–307, after localizing on 300
    assert median_and_p90(all_m)[0] <= 0.3
    assert median_and_p90(first_m)[0] <= 0.3
    assert real_replay[-1].result.status == "localized"
    assert set(real_replay[-1].result.window_tag_ids) <= set(range(300, 308))
