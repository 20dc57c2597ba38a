"""The localizer's errors and settings."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

from app.domain.errors import InvisibleMapError, ParameterError
from app.domain.mapping.params import SlamParams
from app.domain.mapping.slam import (
    pose_sigmas,
)

#: Version of :meth:`LocalizerState.to_json`'s layout; ``from_json`` refuses others.
STATE_VERSION = 1

#: σ of a marginalized prior whose covariance gtsam could not compute (an indeterminate system,
#: which the window's factors should never make): [rot rad, trans m], so wide it barely counts.
FALLBACK_PRIOR_SIGMAS = pose_sigmas(rot_rad=math.pi, trans_m=100.0)

Status = Literal["not_localized", "localized"]


# --------------------------------------------------------------------------- errors


class LocalizationUpdateError(InvisibleMapError):
    """Raised when a localization update is malformed or does not fit the session's state.

    ``field`` names where (``poses[3].timestamp``, ``tag_data[0][1].tag_id``); the state passed to
    :func:`update` is never changed (the function is pure).
    """

    def __init__(self, field: str, reason: str) -> None:
        self.field = field
        self.reason = reason
        super().__init__(f"{field}: {reason}" if field else reason)


class LocalizerStateError(InvisibleMapError):
    """Raised when a stored :class:`LocalizerState` cannot be read back (a server-side fault)."""


# --------------------------------------------------------------------------- parameters


@dataclass(frozen=True, slots=True, kw_only=True)
class LocalizerParams:
    """How the localizer weighs and windows its measurements. All keyword-only.

    slam                        the map's SLAM parameters: the detection noise model
                                (``tag_position_var_m2``, ``tag_depth_var_ratio``,
                                ``tag_orientation_var_rad2``), the odometry random-walk rates, the
                                gravity variance and the detection screening thresholds.
    map_tag_position_var_m2     variance of each map tag's position per axis, m²: the map is not
                                perfect, and a tag "fixed" at a slightly wrong place must not
                                pull harder than the map deserves.
    map_tag_orientation_var_rad2  variance of each map tag's orientation per axis, rad².
    huber_k                     Huber threshold on the whitened 6-D tag residual (σ units); 0 = off.
    window_keyframes            keyframes kept in the optimized window (≥ 2); older ones are
                                marginalized into a prior.
    max_detections_per_keyframe detections one keyframe takes before a new keyframe starts.
    keyframe_merge_s            detections on poses less than this apart share a keyframe, s.
    recent_poses                odometry poses kept for detections that arrive late (≥ 1).
    max_iterations              Levenberg–Marquardt iteration cap per update.

    Out-of-range values raise :class:`ParameterError`.
    """

    slam: SlamParams = field(default_factory=SlamParams)
    map_tag_position_var_m2: float = 0.05**2
    map_tag_orientation_var_rad2: float = 0.05**2
    huber_k: float = 1.345
    window_keyframes: int = 8
    max_detections_per_keyframe: int = 4
    keyframe_merge_s: float = 1.0
    recent_poses: int = 20
    max_iterations: int = 20

    def __post_init__(self) -> None:
        for name in ("map_tag_position_var_m2", "map_tag_orientation_var_rad2", "keyframe_merge_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ParameterError(f"{name} must be finite and ≥ 0")
        if not (math.isfinite(self.huber_k) and self.huber_k >= 0):
            raise ParameterError("huber_k must be finite and ≥ 0 (0 = off)")
        if self.window_keyframes < 2:
            raise ParameterError("window_keyframes must be ≥ 2")
        if self.max_detections_per_keyframe < 1:
            raise ParameterError("max_detections_per_keyframe must be ≥ 1")
        if self.recent_poses < 1:
            raise ParameterError("recent_poses must be ≥ 1")
        if self.max_iterations < 1:
            raise ParameterError("max_iterations must be ≥ 1")
