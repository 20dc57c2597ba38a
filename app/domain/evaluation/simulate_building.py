"""Several simulated mapping sessions of one building, each in its own world frame (issue 15).

    walks = simulate_building_sessions(SimulationConfig(num_poses=600), count=5)
    sessions = [parse_session(s.upload) for s in walks.sessions]
    walks.world_T_tag_true                      # the building's tags, building frame

The building comes from ``config.seed``; walk ``k`` gets its own seed (its route choices, hand
motion, odometry drift and tag noise). Every walk starts at the building's first junction, as
people entering by the same door would, and explores from there. As ARKit does, each walk's
odometry is written in a world frame of its own: gravity-aligned (+y up) but turned about +y by a
random heading and moved by a random offset from the building frame, so a map of several walks must
find how they fit together (``app.domain.mapping.joint``).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from app.domain.errors import ParameterError
from app.domain.evaluation.simulate import (
    Building,
    SimulatedSession,
    SimulationConfig,
    build_building,
    record_walk,
)
from app.domain.frames import (
    FloatArray,
    make_pose,
    rotation_about_y,
)

#: Largest offset of a walk's world origin from the building's, per horizontal axis, m.
MAX_ORIGIN_OFFSET_M = 50.0


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class SimulatedBuilding:
    """Walks of one building. ``sessions[k].world_T_phone_true`` and ``world_T_tag_true`` are in
    the building frame; ``world_T_building[k]`` is where walk ``k``'s odometry frame puts it (the
    upload's odometry is ``world_T_building[k] @ world_T_phone_odometry``)."""

    building: Building
    sessions: tuple[SimulatedSession, ...]
    world_T_building: tuple[FloatArray, ...]

    @property
    def world_T_tag_true(self) -> dict[int, FloatArray]:
        return dict(self.building.world_T_tag)


def simulate_building_sessions(config: SimulationConfig, *, count: int) -> SimulatedBuilding:
    """``count`` walks of the building of ``config`` (see the module docstring); deterministic
    for a given config and count (walk ``k`` does not depend on ``count``)."""
    if count < 1:
        raise ParameterError(f"count must be ≥ 1, got {count}")
    building = build_building(
        config, np.random.default_rng(np.random.SeedSequence(config.seed).spawn(6)[0])
    )
    sessions, frames = [], []
    for k in range(count):
        walk_config = dataclasses.replace(
            config, seed=_walk_seed(config.seed, k), map_id=f"{config.map_id}-{k + 1}"
        )
        streams = np.random.SeedSequence(walk_config.seed).spawn(7)
        rng_walk, rng_odometry, rng_tags, rng_outliers, rng_poi, rng_frame = (
            np.random.default_rng(s) for s in streams[1:]
        )
        world_T_building = (
            np.eye(4)
            if k == 0
            else make_pose(
                rotation_about_y(float(rng_frame.uniform(-math.pi, math.pi))),
                [
                    float(rng_frame.uniform(-MAX_ORIGIN_OFFSET_M, MAX_ORIGIN_OFFSET_M)),
                    0.0,
                    float(rng_frame.uniform(-MAX_ORIGIN_OFFSET_M, MAX_ORIGIN_OFFSET_M)),
                ],
            )
        )
        sessions.append(
            record_walk(
                walk_config,
                building,
                (rng_walk, rng_odometry, rng_tags, rng_outliers, rng_poi),
                world_T_upload=world_T_building,
            )
        )
        frames.append(world_T_building)
    return SimulatedBuilding(
        building=building, sessions=tuple(sessions), world_T_building=tuple(frames)
    )


def _walk_seed(building_seed: int, k: int) -> int:
    return int(np.random.SeedSequence([building_seed, k + 1]).generate_state(1)[0])
