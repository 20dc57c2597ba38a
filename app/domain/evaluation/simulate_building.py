"""Several simulated mapping sessions of one building, each in its own world frame (issues 15, 25).

    walks = simulate_building_sessions(SimulationConfig(num_poses=600), count=5)
    sessions = [parse_session(s.upload) for s in walks.sessions]
    walks.world_T_tag_true                      # the building's tags, building frame
    mixed = simulate_building_sessions(config, count=4, styles=MIXED_WALKS)   # walks that differ

The building comes from ``config.seed``; walk ``k`` gets its own seed (its route choices, hand
motion, odometry drift and tag noise). Every walk starts at the building's first junction, as
people entering by the same door would, and explores from there. As ARKit does, each walk's
odometry is written in a world frame of its own: gravity-aligned (+y up) but turned about +y by a
random heading and moved by a random offset from the building frame, so a map of several walks must
find how they fit together (``app.domain.mapping.joint``).

Real walks of one building differ (issue 25): one person's phone drifts more, another's odometry
runs long, a third walks past the tags without turning to them. A :class:`WalkStyle` per walk
says how its walk differs from ``config``; :data:`MIXED_WALKS` is the building of issue 25's
simulation: a walk as configured, one 3× noisier, one whose odometry is 2% too long, and one
walked obliquely to the tags.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
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
#: How far off the tags' normals an oblique walk may still detect them, deg (the app's detector
#: finds tags at up to ~75°; a walk that turns the phone to the tags sees them within 60°).
OBLIQUE_MAX_VIEW_ANGLE_DEG = 75.0
#: σ of the phone's yaw swing of an oblique walk: held ahead, along the corridor, rad.
OBLIQUE_LOOK_AROUND_RAD = 0.15
#: The noise fields a walk's ``noise_scale`` multiplies (σ's, so the variances grow by its square).
NOISE_FIELDS = (
    "odom_translation_drift_m_per_sqrt_s",
    "odom_vertical_drift_m_per_sqrt_s",
    "odom_rotation_drift_rad_per_sqrt_s",
    "odom_tilt_error_rad",
    "tag_position_noise_m_at_1m",
    "tag_rotation_noise_rad",
    "corner_noise_px",
)


@dataclass(frozen=True, slots=True, kw_only=True)
class WalkStyle:
    """How one walk differs from the building's ``SimulationConfig``.

        WalkStyle()                          # as configured
        WalkStyle(noise_scale=3.0)           # every noise σ 3× larger (odometry and tags)
        WalkStyle(odom_scale_error=0.02)     # odometry 2% too long (a systematic error)
        WalkStyle(oblique=True)              # the phone held ahead: tags seen in passing, obliquely

    noise_scale: multiplies every noise σ of :data:`NOISE_FIELDS`, dimensionless, > 0.
    odom_scale_error: ``SimulationConfig.odom_scale_error`` of the walk, dimensionless.
    oblique: the walker never turns the phone toward a tag (``look_at_tags`` False, a small swing)
        and the detector reports tags up to ``OBLIQUE_MAX_VIEW_ANGLE_DEG`` off their normal, where
        PnP's orientation is poorest (its noise grows as 1 / cos of the view angle).
    """

    noise_scale: float = 1.0
    odom_scale_error: float = 0.0
    oblique: bool = False

    def __post_init__(self) -> None:
        if not (math.isfinite(self.noise_scale) and self.noise_scale > 0):
            raise ParameterError(f"noise_scale must be > 0, got {self.noise_scale!r}")

    def apply(self, config: SimulationConfig) -> SimulationConfig:
        """``config`` as this walk is recorded."""
        changes: dict[str, object] = {
            name: getattr(config, name) * self.noise_scale for name in NOISE_FIELDS
        }
        changes["odom_scale_error"] = self.odom_scale_error
        if self.oblique:
            changes.update(
                look_at_tags=False,
                look_around_rad=OBLIQUE_LOOK_AROUND_RAD,
                max_view_angle_deg=OBLIQUE_MAX_VIEW_ANGLE_DEG,
            )
        return dataclasses.replace(config, **changes)  # type: ignore[arg-type]

    @property
    def label(self) -> str:
        """A short description: ``"as configured"``, ``"3× noisier"``, ``"odometry +2%"``…"""
        parts = []
        if self.noise_scale != 1.0:
            parts.append(f"{self.noise_scale:g}× noisier")
        if self.odom_scale_error:
            parts.append(f"odometry {self.odom_scale_error:+.0%}")
        if self.oblique:
            parts.append("oblique to the tags")
        return ", ".join(parts) or "as configured"


#: Issue 25's building: four walks that differ as real walks do.
MIXED_WALKS = (
    WalkStyle(),
    WalkStyle(noise_scale=3.0),
    WalkStyle(odom_scale_error=0.02),
    WalkStyle(oblique=True),
)


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class SimulatedBuilding:
    """Walks of one building. ``sessions[k].world_T_phone_true`` and ``world_T_tag_true`` are in
    the building frame; ``world_T_building[k]`` is where walk ``k``'s odometry frame puts it (the
    upload's odometry is ``world_T_building[k] @ world_T_phone_odometry``)."""

    building: Building
    sessions: tuple[SimulatedSession, ...]
    world_T_building: tuple[FloatArray, ...]
    styles: tuple[WalkStyle, ...] = ()

    @property
    def world_T_tag_true(self) -> dict[int, FloatArray]:
        return dict(self.building.world_T_tag)


def simulate_building_sessions(
    config: SimulationConfig, *, count: int, styles: Sequence[WalkStyle] = ()
) -> SimulatedBuilding:
    """``count`` walks of the building of ``config`` (see the module docstring); deterministic
    for a given config and count (walk ``k`` does not depend on ``count``). ``styles[k]`` says
    how walk ``k`` differs (walks beyond the styles given are as configured); a style changes
    how its walk is recorded, not its route choices' random draws."""
    if count < 1:
        raise ParameterError(f"count must be ≥ 1, got {count}")
    if len(styles) > count:
        raise ParameterError(f"{len(styles)} walk styles for {count} walks")
    building = build_building(
        config, np.random.default_rng(np.random.SeedSequence(config.seed).spawn(6)[0])
    )
    sessions, frames = [], []
    for k in range(count):
        style = styles[k] if k < len(styles) else WalkStyle()
        walk_config = dataclasses.replace(
            style.apply(config), seed=_walk_seed(config.seed, k), map_id=f"{config.map_id}-{k + 1}"
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
        building=building,
        sessions=tuple(sessions),
        world_T_building=tuple(frames),
        styles=tuple(styles[k] if k < len(styles) else WalkStyle() for k in range(count)),
    )


def _walk_seed(building_seed: int, k: int) -> int:
    return int(np.random.SeedSequence([building_seed, k + 1]).generate_state(1)[0])
