"""SLAM hyperparameters and detection-rejection thresholds, each with its unit in its name.

    SlamParams()                                        # the documented defaults
    SlamParams().with_overrides({"tag_position_var_m2": "1e-4"})   # any value the solver takes
    SlamParams().with_checked_overrides({"huber_k": "2"})  # from outside (``--param``, the API):
                                                        # each value within PARAM_RANGES too

The paper's four hyperparameters are the four variances below (tag position, tag orientation,
odometry linear, odometry angular) plus the gravity variance. Odometry variances are *rates*: the
variance of the relative motion between two poses is the rate times the time between them, so the
noise of an odometry factor grows with its time span (a random walk).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from app.domain.errors import ParameterError

#: The app's printed AprilTags: side of the black square, m.
DEFAULT_TAG_SIZE_M = 0.173

#: Huber threshold on a tag sighting's whitened 6-D residual norm, σ: √χ²₆(0.95) (the value
#: ``noise.robust_threshold(dimension=6)`` computes; a test checks the two agree).
HUBER_K = 3.5484626592017308
#: Weight of the configured variances as the prior of each walk's estimated ones, pseudo-rows
#: (``noise.py``; docs/multi-session.md says which data chose it).
NOISE_PRIOR_DOF = 2.0

#: The noise variances: the paper's four and gravity's. A sweep tunes these, and a map whose
#: variances differ from the defaults is optimized from the defaults' optimum
#: (``slam.optimize_session``).
NOISE_VARIANCE_FIELDS = (
    "tag_position_var_m2",
    "tag_orientation_var_rad2",
    "odom_linear_var_m2_per_s",
    "odom_angular_var_rad2_per_s",
    "gravity_var_rad2",
)


@dataclass(frozen=True, slots=True)
class ParamRange:
    """The values a parameter may be given from outside: ``low`` to ``high`` (inclusive), and
    ``off`` as well when there is one (``huber_k = 0`` turns the Huber loss off).

        ParamRange(0.1, 100.0, "σ", off=0.0)    # str: "0 (off) or 0.1 to 100 σ"
    """

    low: float
    high: float
    unit: str = ""
    off: float | None = None

    def __contains__(self, value: float) -> bool:
        return (self.off is not None and value == self.off) or self.low <= value <= self.high

    def __str__(self) -> str:
        span = f"{self.low:g} to {self.high:g}" + (f" {self.unit}" if self.unit else "")
        return span if self.off is None else f"{self.off:g} (off) or {span}"


#: A noise variance: 1e-12 (σ of 1 µm or 1 µrad) to 1e6 (σ of 1 km or 1000 rad: no information);
#: the paper's grid spans 1e-10 to 10, our sweeps' 1e-8 to 1 (``evaluation.tuning``).
VARIANCE_RANGE = (1e-12, 1e6)
#: The largest tag id a size may be given for (the 32-bit column tag ids are stored in).
MAX_TAG_ID = 2**31 - 1

#: What each number may be set to from outside (the API's rebuild and sweeps, the dashboard's
#: rebuild form, ``--param``): wide enough for every setting that means something (every value
#: the sweeps try, the docs and tests use), narrow enough that none makes the solver run away
#: (a Huber threshold of 1e308, a billion iterations). :meth:`SlamParams.with_checked_overrides`
#: checks them; the constructor only checks what the solver needs (finite, positive), so a map
#: stored with another value is still read.
PARAM_RANGES: dict[str, ParamRange] = {
    "tag_position_var_m2": ParamRange(*VARIANCE_RANGE, "m²"),
    "tag_depth_var_ratio": ParamRange(1.0, 1e6),
    "tag_orientation_var_rad2": ParamRange(*VARIANCE_RANGE, "rad²"),
    "odom_linear_var_m2_per_s": ParamRange(*VARIANCE_RANGE, "m²/s"),
    "odom_angular_var_rad2_per_s": ParamRange(*VARIANCE_RANGE, "rad²/s"),
    "gravity_var_rad2": ParamRange(*VARIANCE_RANGE, "rad²"),
    "huber_k": ParamRange(0.1, 100.0, "σ", off=0.0),
    "stairs_yaw_var_rad2_per_m": ParamRange(1e-8, 1.0, "rad²/m", off=0.0),
    "stairs_linear_var_m2_per_m": ParamRange(1e-8, 1.0, "m²/m", off=0.0),
    "noise_prior_dof": ParamRange(0.0, 1e6, "pseudo-rows"),
    "max_reprojection_px": ParamRange(0.1, 1e4, "px"),
    "max_view_angle_deg": ParamRange(1.0, 90.0, "degrees"),
    "max_distance_m": ParamRange(0.01, 1e3, "m"),
    "keyframe_interval_s": ParamRange(0.0, 3600.0, "s"),
    "tag_size_m": ParamRange(1e-3, 10.0, "m"),
    "max_iterations": ParamRange(1, 10_000),
    "converged_step_m": ParamRange(1e-12, 1.0, "m"),
    "converged_step_rad": ParamRange(1e-12, 1.0, "rad"),
    "relative_error_tol": ParamRange(1e-16, 1.0),
}
#: Each size of ``tag_sizes_m``: the same as ``tag_size_m``'s.
TAG_SIZE_RANGE = PARAM_RANGES["tag_size_m"]


@dataclass(frozen=True, slots=True, kw_only=True)
class SlamParams:
    """Everything that changes the optimized map. All fields are keyword-only.

    Noise (variances; σ = √var):
        tag_position_var_m2         variance of a detected tag's position along each camera axis
                                    *at 1 m distance*, m²; it grows with distance² (see
                                    ``tag_depth_var_ratio`` for the depth axis).
        tag_depth_var_ratio         how much larger the variance along the line of sight is than
                                    across it (PnP depth is the weak axis), dimensionless ≥ 1.
        tag_orientation_var_rad2    variance of a detected tag's orientation about each axis, rad².
        odom_linear_var_m2_per_s    translation random-walk rate of the VIO odometry, m²/s.
        odom_angular_var_rad2_per_s rotation random-walk rate of the VIO odometry, rad²/s.
        gravity_var_rad2            variance of the phone's roll/pitch against gravity, rad².
        huber_k                     Huber threshold on the norm of a tag sighting's whitened 6-D
                                    residual (σ units); 0 = off. The default, 3.548, is
                                    √χ²₆(0.95): a sighting outside the 95% region its noise
                                    allows is down-weighted (``noise.robust_threshold``).

    Stairs (building maps of several walks only; ``joint/stairs.py``): the variance added to a
    walk's odometry per metre it climbs or descends (its own odometry's height: stairs, ramps,
    lifts), on top of its rate × time, so that each walk's link between two floors weighs by
    the flights it climbed, not by the seconds it spent between tag sightings. 0 = off, the
    default: 1.5e-3 and 3e-2 (the simulator's stairs error) make simulated pairs of walks 6–7%
    better on average but the real two-floor pair 1% worse (docs/multi-session.md, issue 37).
        stairs_yaw_var_rad2_per_m   rotation variance (about each axis) per metre climbed, rad²/m.
        stairs_linear_var_m2_per_m  translation variance (per axis) per metre climbed, m²/m.

    Noise estimation (``noise.py``):
        estimate_noise              estimate each walk's odometry and tag variances from its own
                                    residuals (iterated variance-component estimation); the
                                    variances above are then the prior, where the walk's data
                                    cannot tell. False: use them as given (a sweep's trials).
        noise_prior_dof             weight of that prior, in pseudo-rows of measurement, ≥ 0 (0:
                                    the data alone, which can drive a component the walk cannot
                                    check to zero).

    Rejection (a detection that fails any test is left out of the graph and reported):
        max_reprojection_px         RMS distance between the detected corners and those projected
                                    from ``tag_pose`` with the camera intrinsics and tag size, px.
        max_view_angle_deg          angle between the tag's normal and the line to the camera, deg.
        max_distance_m              camera-to-tag distance, m.

    Graph:
        keyframe_interval_s         longest time between two consecutive phone poses of the factor
                                    graph, s. Poses a used tag detection hangs on, the first and
                                    the last are always in it; others only as needed to keep
                                    consecutive graph poses at most this far apart. The poses left
                                    out are placed afterwards by interpolating the odometry
                                    correction linearly in time between the graph poses around
                                    them (the mean of a random walk pinned at both ends). 0 puts
                                    every pose in the graph, as the paper does. At 2 s the real
                                    sessions' graphs hold 20–50% of their poses, their tags stay
                                    within 1 cm RMS of the every-pose maps' and sweeps run 3–4×
                                    faster (README, "Keyframes").

    Geometry and solver:
        tag_size_m                  side of the tags' black square, m; ``tag_sizes_m`` per tag id.
        max_iterations              Levenberg–Marquardt iteration cap.
        converged_step_m            LM stops when no pose or tag moved by more than this in an
        converged_step_rad          iteration, m, and turned by more than this, rad: a criterion
                                    in metres and radians, since on a cost surface as flat as a
                                    walk's a small relative drop of the cost can still be
                                    decimetres from the optimum.
        relative_error_tol          LM also stops when an iteration lowers the error by less than
                                    this fraction (a numerical stall; 1e-9).
        compute_marginals           whether to compute tag-pose covariances.
    """

    tag_position_var_m2: float = 1e-4
    tag_depth_var_ratio: float = 10.0
    tag_orientation_var_rad2: float = 1e-1
    odom_linear_var_m2_per_s: float = 1e-3
    odom_angular_var_rad2_per_s: float = 1e-4
    gravity_var_rad2: float = 1e-4
    huber_k: float = HUBER_K
    stairs_yaw_var_rad2_per_m: float = 0.0
    stairs_linear_var_m2_per_m: float = 0.0
    estimate_noise: bool = True
    noise_prior_dof: float = NOISE_PRIOR_DOF

    max_reprojection_px: float = 8.0
    max_view_angle_deg: float = 70.0
    max_distance_m: float = 5.0

    keyframe_interval_s: float = 2.0

    tag_size_m: float = DEFAULT_TAG_SIZE_M
    tag_sizes_m: Mapping[int, float] = field(default_factory=dict)
    max_iterations: int = 100
    converged_step_m: float = 1e-4
    converged_step_rad: float = 1e-5
    relative_error_tol: float = 1e-9
    compute_marginals: bool = True

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, float) and not math.isfinite(value):
                raise ParameterError(f"{f.name} must be finite, got {value}")
        positive = [
            "tag_position_var_m2",
            "tag_orientation_var_rad2",
            "odom_linear_var_m2_per_s",
            "odom_angular_var_rad2_per_s",
            "gravity_var_rad2",
            "max_reprojection_px",
            "max_distance_m",
            "tag_size_m",
            "relative_error_tol",
            "converged_step_m",
            "converged_step_rad",
        ]
        for name in positive:
            if getattr(self, name) <= 0:
                raise ParameterError(f"{name} must be > 0, got {getattr(self, name)}")
        if self.tag_depth_var_ratio < 1:
            raise ParameterError(f"tag_depth_var_ratio must be ≥ 1, got {self.tag_depth_var_ratio}")
        if self.keyframe_interval_s < 0:
            raise ParameterError(
                f"keyframe_interval_s must be ≥ 0 (0 keeps every pose), got "
                f"{self.keyframe_interval_s}"
            )
        if self.huber_k < 0:
            raise ParameterError(f"huber_k must be ≥ 0 (0 disables it), got {self.huber_k}")
        for name in ("stairs_yaw_var_rad2_per_m", "stairs_linear_var_m2_per_m"):
            if getattr(self, name) < 0:
                raise ParameterError(
                    f"{name} must be ≥ 0 (0 turns it off), got {getattr(self, name)}"
                )
        if self.noise_prior_dof < 0:
            raise ParameterError(f"noise_prior_dof must be ≥ 0, got {self.noise_prior_dof}")
        if not 0 < self.max_view_angle_deg <= 90:
            raise ParameterError(
                f"max_view_angle_deg must be in (0, 90], got {self.max_view_angle_deg}"
            )
        if self.max_iterations < 1:
            raise ParameterError(f"max_iterations must be ≥ 1, got {self.max_iterations}")
        for tag_id, size_m in self.tag_sizes_m.items():
            if not 0 < size_m < math.inf:
                raise ParameterError(f"tag_sizes_m[{tag_id}] must be finite and > 0, got {size_m}")

    def with_checked_overrides(self, overrides: Mapping[str, Any]) -> SlamParams:
        """:meth:`with_overrides` for values from outside (the API, the dashboard, ``--param``):
        each given value must also lie in its :data:`PARAM_RANGES`. ParameterError naming the
        first parameter at fault and its range."""
        for name, raw in overrides.items():
            try:
                changed = self.with_overrides({name: raw})
            except ParameterError as err:
                if name not in PARAM_RANGES:
                    raise
                raise ParameterError(f"{err} (it takes {PARAM_RANGES[name]})") from err
            changed.check_ranges([name])
        return self.with_overrides(overrides)

    def check_ranges(self, names: Iterable[str] | None = None) -> SlamParams:
        """``self`` if each of ``names`` (every field when None) lies in its
        :data:`PARAM_RANGES`, else ParameterError naming the first that does not and its range."""
        checked = [f.name for f in dataclasses.fields(self)] if names is None else names
        for name in checked:
            value = getattr(self, name)
            if name == "tag_sizes_m":
                for tag_id, size_m in value.items():
                    if not 0 <= tag_id <= MAX_TAG_ID:
                        raise ParameterError(
                            f"tag_sizes_m: a tag id is 0 to {MAX_TAG_ID}, got {_shown(tag_id)}"
                        )
                    if size_m not in TAG_SIZE_RANGE:
                        raise ParameterError(
                            f"tag_sizes_m[{tag_id}] must be {TAG_SIZE_RANGE}, got {_shown(size_m)}"
                        )
            elif name in PARAM_RANGES and value not in PARAM_RANGES[name]:
                raise ParameterError(f"{name} must be {PARAM_RANGES[name]}, got {_shown(value)}")
        return self

    def with_default_variances(self) -> SlamParams:
        """A copy with every noise variance (:data:`NOISE_VARIANCE_FIELDS`) at its default."""
        defaults = SlamParams()
        return dataclasses.replace(
            self, **{name: getattr(defaults, name) for name in NOISE_VARIANCE_FIELDS}
        )

    @property
    def has_default_variances(self) -> bool:
        """Whether every noise variance is at its default (the other fields may differ)."""
        defaults = SlamParams()
        return all(getattr(self, n) == getattr(defaults, n) for n in NOISE_VARIANCE_FIELDS)

    def tag_size_for(self, tag_id: int) -> float:
        """Side of tag ``tag_id``, m."""
        return float(self.tag_sizes_m.get(tag_id, self.tag_size_m))

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready parameters (tag ids become string keys)."""
        out = dataclasses.asdict(self)
        out["tag_sizes_m"] = {str(k): v for k, v in self.tag_sizes_m.items()}
        return out

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> SlamParams:
        """Inverse of :meth:`to_dict`; unknown names raise :class:`ParameterError`."""
        return cls().with_overrides(values)

    def with_overrides(self, overrides: Mapping[str, Any]) -> SlamParams:
        """A copy with some fields replaced; values may be strings (``"1e-4"``, ``"true"``).

        ``tag_sizes_m`` takes a mapping, or a string ``"300:0.15,301:0.2"``.
        """
        types = {f.name: f.type for f in dataclasses.fields(self)}
        changes: dict[str, Any] = {}
        for name, raw in overrides.items():
            if name not in types:
                known = ", ".join(sorted(types))
                raise ParameterError(f"unknown parameter {name!r}; known: {known}")
            changes[name] = _coerce(name, str(types[name]), raw)
        return dataclasses.replace(self, **changes)


def _coerce(name: str, type_name: str, raw: Any) -> Any:
    try:
        if type_name == "bool":
            if isinstance(raw, bool):
                return raw
            text = str(raw).strip().lower()
            if text in {"1", "true", "yes", "on"}:
                return True
            if text in {"0", "false", "no", "off"}:
                return False
            raise ValueError(f"not a boolean: {raw!r}")
        if type_name == "int":
            if isinstance(raw, float) and not raw.is_integer():
                raise ValueError(f"not an integer: {raw!r}")
            return int(raw)
        if type_name == "float":
            if isinstance(raw, bool):
                raise ValueError(f"not a number: {raw!r}")
            return float(raw)
        if isinstance(raw, Mapping):
            return {int(k): float(v) for k, v in raw.items()}
        pairs = [p for p in str(raw).split(",") if p.strip()]
        return {int(k): float(v) for k, v in (p.split(":") for p in pairs)}
    except (TypeError, ValueError) as err:
        reason = _brief(str(err).partition(";")[0])
        raise ParameterError(
            f"parameter {name}: cannot use {_brief(repr(raw))} ({reason})"
        ) from err


#: The most characters of a refused value an error shows.
_SHOWN_CHARS = 60


def _brief(text: str) -> str:
    """``text`` cut to :data:`_SHOWN_CHARS` (a refused value can be 5,000 digits)."""
    return text if len(text) <= _SHOWN_CHARS else text[: _SHOWN_CHARS - 1] + "…"


def _shown(value: float) -> str:
    """A parameter's value in an error: ``%g`` (an integer of 400 digits as its digit count)."""
    try:
        return f"{value:g}"
    except OverflowError:
        return f"a number of {len(str(abs(int(value))))} digits"
