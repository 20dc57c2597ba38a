"""Odometry drift: the truth under an accumulating drift (``drift_odometry``), and issue 37's
errors that come in stretches (the stairs, fast turns)."""

from __future__ import annotations

import math

import numpy as np

from app.domain.frames import FloatArray, so3_exp

from .config import (
    FAST_TURN_RAD_PER_S,
    STAIRS_LANDING_S,
    STAIRS_VERTICAL_SPEED_M_PER_S,
    TILT_CORRELATION_S,
    BoolArray,
    SimulationConfig,
)
from .numeric import gaussian_smooth, rotations_about_y, smooth_noise


def drift_odometry(
    config: SimulationConfig, world_T_phone_true: FloatArray, rng: np.random.Generator
) -> FloatArray:
    """The odometry: the truth under an accumulating drift that is zero at the first pose.

    odometry_i = [tilt_i · Ry(ψ_i) · R_i,  p_i + Σ_{k<i} (((1 + s) Ry(ψ_k) − I) Δp_k + δ_k)]: the
    heading error ψ (a random walk) turns each later step of the true path, s
    (``odom_scale_error``) stretches it, δ is the translation random walk, and the tilt error
    (about the world's horizontal axes) is bounded: ARKit keeps roll and pitch on gravity. All
    three are zero at the first pose, so both world frames coincide there.
    """
    n = world_T_phone_true.shape[0]
    dt_s = 1.0 / config.rate_hz
    sqrt_dt = math.sqrt(dt_s)
    yaw_steps = rng.standard_normal(n - 1) * config.odom_rotation_drift_rad_per_sqrt_s * sqrt_dt
    translation_steps = rng.standard_normal((n - 1, 3)) * sqrt_dt
    translation_steps[:, [0, 2]] *= config.odom_translation_drift_m_per_sqrt_s
    translation_steps[:, 1] *= config.odom_vertical_drift_m_per_sqrt_s
    correlation = TILT_CORRELATION_S * config.rate_hz
    tilt_rad = np.stack(
        [
            smooth_noise(rng, n, config.odom_tilt_error_rad, correlation),
            np.zeros(n),
            smooth_noise(rng, n, config.odom_tilt_error_rad, correlation),
        ],
        axis=1,
    )
    # Zero at the first pose (ARKit sets its world frame there); σ = odom_tilt_error_rad later on.
    tilt_rad = (tilt_rad - tilt_rad[:1]) / math.sqrt(2)

    step_scale = np.full(n - 1, 1.0 + config.odom_scale_error)
    if config.stairs_scale_error_sigma or config.stairs_yaw_error_rad:
        stairs_scale, stairs_yaw = _stairs_errors(config, world_T_phone_true)
        step_scale += stairs_scale
        yaw_steps = yaw_steps + stairs_yaw
    if config.fast_turn_yaw_error_ratio:
        yaw_steps = yaw_steps + _fast_turn_errors(config, world_T_phone_true)

    yaw_drift_rad = np.concatenate([[0.0], np.cumsum(yaw_steps)])
    drift_R = rotations_about_y(yaw_drift_rad)
    true_steps = np.diff(world_T_phone_true[:, :3, 3], axis=0)
    turned_steps = (
        step_scale[:, None] * np.einsum("nij,nj->ni", drift_R[:-1], true_steps) - true_steps
    )
    offset = np.concatenate([np.zeros((1, 3)), np.cumsum(turned_steps + translation_steps, axis=0)])

    odometry = world_T_phone_true.copy()
    odometry[:, :3, :3] = so3_exp(tilt_rad) @ drift_R @ world_T_phone_true[:, :3, :3]
    odometry[:, :3, 3] += offset
    return odometry


def stretch_rng(config: SimulationConfig, stream: int) -> np.random.Generator:
    """A random stream of issue 37's error sources of its own (drawn only when they are on), so
    switching one on changes no other draw of the walk."""
    return np.random.default_rng(np.random.SeedSequence([config.seed, 37, stream]))


def stairs_traversals(config: SimulationConfig, world_T_phone_true: FloatArray) -> list[slice]:
    """The odometry steps (rows of the (N − 1) steps) of each traversal of the stairs: where the
    true path climbs or descends faster than ``STAIRS_VERTICAL_SPEED_M_PER_S`` (the gait's bob
    smoothed away), runs closer than ``STAIRS_LANDING_S`` joined (the landing)."""
    height_m = gaussian_smooth(world_T_phone_true[:, 1, 3], 0.5 * config.rate_hz)
    climbing = np.abs(np.diff(height_m)) * config.rate_hz > STAIRS_VERTICAL_SPEED_M_PER_S
    return _runs(climbing, round(STAIRS_LANDING_S * config.rate_hz))


def _runs(flags: BoolArray, join_gap: int) -> list[slice]:
    """The runs of True in ``flags`` as slices, runs less than ``join_gap`` apart joined."""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], flags.astype(np.int8), [0]])))
    runs: list[list[int]] = []
    for start, stop in zip(edges[::2].tolist(), edges[1::2].tolist(), strict=True):
        if runs and start - runs[-1][1] < join_gap:
            runs[-1][1] = stop
        else:
            runs.append([start, stop])
    return [slice(a, b) for a, b in runs]


def _stairs_errors(
    config: SimulationConfig, world_T_phone_true: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """(N − 1,) the extra scale of each odometry step and (N − 1,) the extra heading of each step,
    rad: per traversal of the stairs, a scale error of σ ``stairs_scale_error_sigma`` on its steps
    and a heading error of σ ``stairs_yaw_error_rad`` spread evenly over them. The real figures:
    :data:`REGION_ERROR_SOURCES` ("stairs")."""
    rng = stretch_rng(config, 0)
    n = world_T_phone_true.shape[0]
    scale, yaw = np.zeros(n - 1), np.zeros(n - 1)
    for run in stairs_traversals(config, world_T_phone_true):
        scale[run] = rng.normal(0.0, config.stairs_scale_error_sigma)
        yaw[run] = rng.normal(0.0, config.stairs_yaw_error_rad) / (run.stop - run.start)
    return scale, yaw


def _fast_turn_errors(config: SimulationConfig, world_T_phone_true: FloatArray) -> FloatArray:
    """(N − 1,) the extra heading of each odometry step, rad: each fast turn (the phone's yaw rate
    above ``FAST_TURN_RAD_PER_S``, a turn toward a wall or round a corner) is over- or
    under-counted by a factor of σ ``fast_turn_yaw_error_ratio`` drawn for that turn. The real
    figures: :data:`REGION_ERROR_SOURCES` ("fast turns")."""
    forward = -world_T_phone_true[:, :3, 2]
    yaw_rad = np.unwrap(np.arctan2(-forward[:, 0], -forward[:, 2]))
    turn_rad = np.diff(yaw_rad)
    fast = np.abs(turn_rad) * config.rate_hz > FAST_TURN_RAD_PER_S
    rng = stretch_rng(config, 1)
    error = np.zeros_like(turn_rad)
    for run in _runs(fast, 1):
        error[run] = rng.normal(0.0, config.fast_turn_yaw_error_ratio) * turn_rad[run]
    return error
