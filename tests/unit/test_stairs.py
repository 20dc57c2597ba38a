"""Issue 37: a building map trusts each walk's odometry on the stairs by the height it climbed,
not by the seconds it spent between sightings (``app/domain/mapping/joint/stairs.py``)."""

from __future__ import annotations

import dataclasses
import math
from functools import cache
from pathlib import Path

import numpy as np
import pytest

from app.domain.evaluation.regions import region_errors, tag_regions
from app.domain.evaluation.simulate import SimulationConfig
from app.domain.evaluation.simulate_building import simulate_building_sessions
from app.domain.frames import FloatArray, make_pose, rotation_about_y
from app.domain.mapping.joint import optimize_sessions
from app.domain.mapping.joint.stairs import (
    MIN_CLIMB_M,
    stair_links,
    stairs_variance,
    tag_levels,
    walk_climbs,
)
from app.domain.mapping.params import SlamParams
from app.domain.mapping.slam import GraphInputs
from app.domain.upload.session import Session, TagDetections, load_session, parse_session

DATA_DIR = Path(__file__).parents[2] / "data"

#: The rule on: the simulator's stairs error (0.07 rad a 3.3 m traversal, 4% of its length).
STAIRS = SlamParams(stairs_yaw_var_rad2_per_m=1.5e-3, stairs_linear_var_m2_per_m=3e-2)


def _session(height_m: FloatArray, step_s: float = 0.5) -> Session:
    """A walk along +x at 1 m/s with the given odometry heights and no sighting."""
    n = len(height_m)
    world_T_phone = np.stack(
        [make_pose(np.eye(3), [0.5 * i, h, 0.0]) for i, h in enumerate(height_m)]
    )
    empty = {
        f.name: np.zeros((0, *shape), dtype=dtype)
        for f, shape, dtype in zip(
            dataclasses.fields(TagDetections),
            [(), (), (), (), (), (4, 4), (4, 4), (4,), (4, 2), (3,), (4,), (7, 7)],
            [np.int64] * 4 + [np.float64] * 8,
            strict=True,
        )
    }
    return Session(
        map_id="synthetic",
        pose_id=np.arange(n, dtype=np.int64),
        timestamp_s=np.arange(n) * step_s,
        world_T_phone=world_T_phone,
        detections=TagDetections(**empty),
    )


def _raised_phone(seconds: float, step_s: float = 0.5) -> FloatArray:
    """1.3 m, raised by 0.4 m toward a tag for 2 s every 10 s."""
    t = np.arange(0.0, seconds, step_s)
    return np.where((t % 10.0) < 2.0, 1.7, 1.3)


def test_a_climb_is_where_the_walk_changes_floor_not_where_the_phone_is_raised() -> None:
    flat = _raised_phone(60.0)
    stairs = np.linspace(0.0, 3.3, 21)[1:]  # 3.3 m in 10 s
    session = _session(np.concatenate([flat, flat[-1] + stairs, flat + 3.3]))
    climbs = walk_climbs(session)
    assert len(climbs) == 1
    (climb,) = climbs
    assert climb.height_m == pytest.approx(3.3, abs=0.5)
    assert climb.climbed_m == pytest.approx(3.3, abs=0.5)
    assert climb.first_pose >= 100
    assert climb.stop_pose <= 160
    assert walk_climbs(_session(flat)) == []
    added = stairs_variance(session, STAIRS)
    assert added.shape == (session.num_poses, 2)
    assert added[:, 1].sum() == pytest.approx(STAIRS.stairs_yaw_var_rad2_per_m * climb.climbed_m)
    assert added[:, 0].sum() == pytest.approx(STAIRS.stairs_linear_var_m2_per_m * climb.climbed_m)
    assert not added[: climb.first_pose].any()
    assert not added[climb.stop_pose :].any()
    assert not stairs_variance(session, SlamParams()).any()  # off by default


@cache
def _real(name: str) -> Session:
    path = DATA_DIR / "sessions" / f"{name}.json"
    if not path.exists():
        path = DATA_DIR.parents[1] / "shared" / "data" / "sessions" / f"{name}.json"
    return load_session(path)


@pytest.mark.parametrize(
    ("name", "flights"),
    [("straight_209_occam", 4), ("floor_2_straight", 0), ("occam_room", 0)],
)
def test_the_real_walks_climbs_are_their_stairs(name: str, flights: int) -> None:
    """straight_209_occam goes down two flights to the lower floor and back up two; the walks
    of one floor, whose phones rise and fall by up to 1.6 m, climb nothing."""
    climbs = walk_climbs(_real(name))
    assert len(climbs) == flights
    assert all(abs(c.height_m) >= MIN_CLIMB_M for c in climbs)
    if flights:
        assert sum(c.height_m for c in climbs) == pytest.approx(0.0, abs=1.0)  # back up again


def test_a_step_between_keyframes_adds_its_poses_variance() -> None:
    session = _session(
        np.concatenate([np.full(40, 1.3), 1.3 + np.linspace(0, 3, 20), 4.3 + np.zeros(40)])
    )
    added = stairs_variance(session, STAIRS)
    inputs = GraphInputs(
        session, SlamParams(keyframe_interval_s=2.0), odometry_added_variance=added
    )
    plain = GraphInputs(session, SlamParams(keyframe_interval_s=2.0))
    assert np.array_equal(inputs.keyframes, plain.keyframes)
    summed = np.add.reduceat(added, inputs.keyframes)[:-1]
    np.testing.assert_allclose(inputs.odometry_added_variance, summed, atol=1e-15)
    assert not plain.odometry_added_variance.any()


# --------------------------------------------------------------------------- a simulated pair


def _yaw_error_on_the_stairs(session: Session, yaw_rad: float) -> Session:
    """``session`` with its odometry turned by ``yaw_rad`` about the vertical half-way up its
    first climb (the heading error real odometry makes on the stairs)."""
    climb = walk_climbs(session)[0]
    middle = (climb.first_pose + climb.stop_pose) // 2
    pivot = session.world_T_phone[middle, :3, 3]
    turn = make_pose(rotation_about_y(yaw_rad), pivot) @ make_pose(np.eye(3), -pivot)
    world_T_phone = session.world_T_phone.copy()
    world_T_phone[middle:] = turn @ world_T_phone[middle:]
    return dataclasses.replace(session, world_T_phone=world_T_phone)


def _unseen_around_the_stairs(session: Session, margin_s: float) -> Session:
    """``session`` without its sightings from ``margin_s`` before its first climb to
    ``margin_s`` after (a walk that saw no tag near the stairs)."""
    climb = walk_climbs(session)[0]
    t = session.timestamp_s
    d = session.detections
    keep = (d.timestamp_s < t[climb.first_pose] - margin_s) | (
        d.timestamp_s > t[climb.stop_pose - 1] + margin_s
    )
    columns = {f.name: getattr(d, f.name)[keep] for f in dataclasses.fields(TagDetections)}
    return dataclasses.replace(session, detections=TagDetections(**columns))


@cache
def _pair() -> tuple[list[Session], dict[int, FloatArray]]:
    """Two walks of a two-floor building, each changing floor once: ``a``'s odometry turns by 4°
    on the stairs and it sees tags close to them; ``b``'s stairs are as its noise says, but it
    sees no tag for 60 s either side of them, so by time alone its link is the looser."""
    config = SimulationConfig(num_poses=2400, two_floors=True, seed=0, max_floor_changes=1)
    building = simulate_building_sessions(config, count=2)
    a, b = (parse_session(s.upload) for s in building.sessions)
    sessions = [_yaw_error_on_the_stairs(a, math.radians(4.0)), _unseen_around_the_stairs(b, 60.0)]
    return sessions, building.world_T_tag_true


def _between_floors_m(params: SlamParams) -> tuple[float, float, float]:
    """How far off the walks place one floor against the other: ``a`` alone, ``b`` alone and
    the building map (the map fitted on one floor, the other floor's RMS error; mean both ways)."""
    sessions, truth = _pair()
    joint = optimize_sessions(sessions, params, names=["a", "b"])
    regions = tag_regions(truth)
    errors = []
    for part in joint.parts:
        assert part.alone is not None
        tags = sorted(t for t in part.alone.tag_poses() if t in truth)
        errors.append(region_errors(part.alone.tag_poses(), truth, regions, tags).between_floors_m)
    built = region_errors(joint.map.tag_poses(), truth, regions).between_floors_m
    return errors[0], errors[1], built


def test_the_building_map_joins_the_floors_by_the_climbs_not_by_the_time_unseen() -> None:
    """By time alone, ``a``'s short link (4° off) outweighs ``b``'s long one, and the building map
    places the floors almost as badly as ``a`` alone; with the stairs' variance both links count
    as the flights they are, and it places them clearly better than the worse walk (measured:
    0.79 and 0.54 of ``a``'s error)."""
    a, b, built_by_time = _between_floors_m(SlamParams())
    _, _, built = _between_floors_m(STAIRS)
    assert a > 2 * b  # a's stairs err
    assert built_by_time > 0.75 * a
    assert built < 0.65 * a
    assert built < built_by_time


def test_the_report_says_how_much_each_walk_holds_between_the_levels() -> None:
    sessions, _ = _pair()
    joint = optimize_sessions(sessions, STAIRS, names=["a", "b"])
    links = [link for part in joint.parts for link in part.stair_links]
    assert {link.levels for link in links} == {(0, 1)}
    assert sum(link.share for link in links) == pytest.approx(1.0)
    assert sum(link.share_by_time for link in links) == pytest.approx(1.0)
    a, b = joint.parts
    assert a.stair_links
    assert b.stair_links
    assert b.stair_links[0].duration_s > a.stair_links[0].duration_s + 60.0
    # by time alone a holds the link between the floors; with the stairs' variance, less so
    assert a.stair_links[0].share_by_time > 0.8
    assert 0.4 < a.stair_links[0].share < a.stair_links[0].share_by_time
    assert "joins levels 0 and 1 once" in a.weighting
    assert "by time alone" in b.weighting


def test_each_walks_cost_alone_is_taken_under_the_joint_maps_model() -> None:
    """A walk's cost alone (what its cost in the building map is compared with, step 6) is its
    own optimum's under the same odometry model: with the stairs' variance, lower."""
    sessions, _ = _pair()
    plain = optimize_sessions(sessions, names=["a", "b"])
    stairs = optimize_sessions(sessions, STAIRS, names=["a", "b"])
    for before, after in zip(plain.parts, stairs.parts, strict=True):
        assert before.fit is not None
        assert before.cost_alone == before.fit.cost
        assert after.cost_alone < before.cost_alone


def test_levels_come_from_the_maps_tag_heights() -> None:
    tags = {t: make_pose(np.eye(3), [float(t), y, 0.0]) for t, y in
            [(1, 1.4), (2, 1.2), (3, 3.9), (4, 6.6), (5, 6.4), (6, 6.9)]}  # fmt: skip
    assert tag_levels(tags) == {1: 0, 2: 0, 3: 1, 4: 2, 5: 2, 6: 2}
    session = _session(np.full(10, 1.3))
    assert stair_links(session, np.zeros(0, dtype=bool), tag_levels(tags), []) == []
