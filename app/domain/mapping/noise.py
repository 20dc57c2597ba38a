"""Each walk's noise, estimated from its own residuals: iterated variance-component estimation.

    estimate = result.noise                      # a NoiseEstimate (slam.optimize_session)
    estimate.variances(params)                   # the walk's WalkNoise: what its data support
    robust_threshold(dimension=6)                # √χ²₆(0.95) = 3.548, the tag kernel's k

Why variance components. The map is a weighted least-squares fit of odometry, gravity and tag
sightings; what it looks like depends on how the kinds of measurement are weighed against each
other, and the right weights differ from walk to walk (a phone whose odometry drifts more, a walk
that sees the tags obliquely). Iterated variance-component estimation (Helmert; Förstner 1979;
Koch 1986) finds each kind's variance from the residuals it leaves at the optimum: for a group
``c`` of measurement rows, with ``vᵀPv`` its whitened squared residuals and ``r`` its redundancy
(how many of its rows the other measurements check: ``Σ (1 − h_ii)``, ``h`` the hat matrix's
diagonal), the estimate of its variance factor is ``vᵀPv / r``. Rescale, optimize again, repeat to
a fixed point. Unlike a sweep it needs no ground truth and no metric: only the walk's own data.

The components of a walk:

- ``odom_linear``: the odometry's translation rows;
- ``odom_angular``: the odometry's rotation about gravity (its yaw). The two tilt axes are left out:
  ARKit's world is gravity-aligned, so the measured up vector and the odometry's tilt are one
  measurement, their residuals are zero by construction and would drive the estimate to zero;
- ``tag_position`` and ``tag_orientation``: the translation and rotation rows of the tag sightings.

Gravity is not estimated (same reason: it is the odometry's own tilt).

A prior keeps a component the walk cannot check where it was configured. A walk that sees each
tag once leaves its tag positions almost no redundancy (``r`` ≈ 0): plain VCE then drives that
component to zero, which makes the tags rigid and the odometry absorb everything (observed on
floor_2_straight). With a conjugate (scaled inverse-χ²) prior of ``prior_dof`` pseudo-rows at the
configured variance ``σ₀²``, the estimate is the posterior mode::

    σ² ← (vᵀv + prior_dof · σ₀²) / (r + prior_dof)         (vᵀv unwhitened: vᵀPv · σ²)

A component the walk's data check many times (``r`` ≫ ``prior_dof``) follows the data; one they
cannot check stays near ``σ₀²``.

Robustness: the tag factors carry a Huber kernel whose threshold is the χ² quantile of the
residual's dimension (:func:`robust_threshold`), so it means "a sighting outside the 95% region
its noise allows"; the estimate uses the kernel's weights (IRLS) in both ``vᵀPv`` and ``r``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from app.domain.json_values import finite_or_none
from app.domain.mapping.params import SlamParams

FloatArray = npt.NDArray[np.float64]

#: The estimated components, in the order of every (…, 4) array of this module.
COMPONENTS = ("odom_linear", "odom_angular", "tag_position", "tag_orientation")
#: The ``SlamParams`` variance each component scales.
COMPONENT_FIELDS = (
    "odom_linear_var_m2_per_s",
    "odom_angular_var_rad2_per_s",
    "tag_position_var_m2",
    "tag_orientation_var_rad2",
)
#: The robust kernel's quantile: a whitened residual beyond the 95% region of its χ² is
#: down-weighted.
ROBUST_QUANTILE = 0.95


def chi2_cdf(x: float, dof: int) -> float:
    """P(X ≤ x) for X ~ χ² with ``dof`` degrees of freedom (closed forms: the regularized lower
    incomplete gamma function at integer and half-integer shape)."""
    if dof < 1:
        raise ValueError(f"dof must be ≥ 1, got {dof}")
    if x <= 0:
        return 0.0
    half = x / 2.0
    if dof % 2 == 0:  # Q(k, x/2) = e^(−x/2) Σ_{i<k} (x/2)^i / i!
        term, total = 1.0, 1.0
        for i in range(1, dof // 2):
            term *= half / i
            total += term
        return 1.0 - math.exp(-half) * total
    # odd: P(1/2, x/2) = erf(√(x/2)), then the recurrence P(a + 1) = P(a) − e^(−x/2)(x/2)^a / Γ(a+1)
    p = math.erf(math.sqrt(half))
    a = 0.5
    while a < dof / 2.0:
        p -= math.exp(a * math.log(half) - half - math.lgamma(a + 1.0))
        a += 1.0
    return p


def chi2_quantile(probability: float, dof: int) -> float:
    """The ``probability`` quantile of χ² with ``dof`` degrees of freedom (bisection on
    :func:`chi2_cdf`; ``chi2_quantile(0.95, 6)`` = 12.5916, as scipy's ``chi2.ppf``)."""
    if not 0.0 < probability < 1.0:
        raise ValueError(f"probability must be in (0, 1), got {probability}")
    low, high = 0.0, float(dof)
    while chi2_cdf(high, dof) < probability:
        high *= 2.0
    for _ in range(200):
        middle = 0.5 * (low + high)
        if chi2_cdf(middle, dof) < probability:
            low = middle
        else:
            high = middle
        if high - low < 1e-12 * max(1.0, high):
            break
    return 0.5 * (low + high)


def robust_threshold(*, dimension: int, quantile: float = ROBUST_QUANTILE) -> float:
    """The Huber threshold on the norm of a whitened ``dimension``-D residual: √χ²_dim(quantile),
    in σ units. gtsam applies the kernel to the whitened residual's norm, which for a correct
    noise model is χ-distributed with ``dimension`` degrees of freedom: a one-dimensional
    constant (1.345) on a 6-D norm down-weights most good sightings."""
    return math.sqrt(chi2_quantile(quantile, dimension))


@dataclass(frozen=True, slots=True, kw_only=True)
class WalkNoise:
    """One walk's noise variances, in ``SlamParams``' units (see there)."""

    odom_linear_var_m2_per_s: float
    odom_angular_var_rad2_per_s: float
    tag_position_var_m2: float
    tag_orientation_var_rad2: float

    @classmethod
    def of(cls, params: SlamParams) -> WalkNoise:
        """The configured variances of ``params``."""
        return cls(**{name: float(getattr(params, name)) for name in COMPONENT_FIELDS})

    @classmethod
    def from_array(cls, variances: FloatArray) -> WalkNoise:
        return cls(**{name: float(v) for name, v in zip(COMPONENT_FIELDS, variances, strict=True)})

    def as_array(self) -> FloatArray:
        """(4,) in :data:`COMPONENTS` order."""
        return np.array([getattr(self, name) for name in COMPONENT_FIELDS], dtype=np.float64)

    def scales(self, params: SlamParams) -> FloatArray:
        """(4,) each variance over ``params``' (what the factors multiply their noise by)."""
        return self.as_array() / WalkNoise.of(params).as_array()

    def to_dict(self) -> dict[str, float]:
        return {name: float(getattr(self, name)) for name in COMPONENT_FIELDS}


@dataclass(frozen=True, slots=True, kw_only=True)
class NoiseEstimate:
    """What the variance-component estimation of one walk found.

    scales: (4,) each component's variance over the configured one (:data:`COMPONENTS` order).
    redundancy: (4,) each component's redundancy at the last round, rows (0 to its row count).
    rows: (4,) how many measurement rows each component has.
    chi2_per_redundancy: (4,) ``vᵀPv / r`` at the last round, with the final variances: 1 when
        the estimate has converged and the prior does not pull (NaN with no redundancy).
    rounds: how many optimizations it took; converged: whether the last change of every scale
        was below the tolerance (else the rounds ran out, or the system became indeterminate:
        ``note`` says).
    """

    scales: FloatArray
    redundancy: FloatArray
    rows: FloatArray
    chi2_per_redundancy: FloatArray
    rounds: int
    converged: bool
    note: str = ""

    def variances(self, params: SlamParams) -> WalkNoise:
        """The walk's estimated variances (the configured ones of ``params`` × :attr:`scales`)."""
        return WalkNoise.from_array(WalkNoise.of(params).as_array() * self.scales)

    def to_dict(self, params: SlamParams) -> dict[str, object]:
        """JSON-ready: the variances, and per component its scale, redundancy and rows."""
        return {
            "variances": self.variances(params).to_dict(),
            "components": {
                name: {
                    "scale": float(self.scales[c]),
                    "redundancy": float(self.redundancy[c]),
                    "rows": float(self.rows[c]),
                    "chi2_per_redundancy": finite_or_none(self.chi2_per_redundancy[c]),
                }
                for c, name in enumerate(COMPONENTS)
            },
            "rounds": self.rounds,
            "converged": self.converged,
            "note": self.note,
        }


def noise_estimate_from_dict(values: Mapping[str, Any]) -> NoiseEstimate:
    """Inverse of :meth:`NoiseEstimate.to_dict` (its ``variances`` are derived, not read)."""
    components = values["components"]

    def column(name: str) -> FloatArray:
        return np.array(
            [
                math.nan if components[c][name] is None else float(components[c][name])
                for c in COMPONENTS
            ]
        )

    return NoiseEstimate(
        scales=column("scale"),
        redundancy=column("redundancy"),
        rows=column("rows"),
        chi2_per_redundancy=column("chi2_per_redundancy"),
        rounds=int(values["rounds"]),
        converged=bool(values["converged"]),
        note=str(values.get("note", "")),
    )


def updated_scales(
    scales: FloatArray,
    chi2: FloatArray,
    redundancy: FloatArray,
    *,
    prior_dof: float,
    bounds: tuple[float, float],
) -> FloatArray:
    """(…, 4) the next variance scales: the posterior mode of each component given its whitened
    squared residuals ``chi2`` (with the current ``scales``) and redundancy (module docstring),
    the prior at scale 1 with ``prior_dof`` pseudo-rows, and clipped to ``bounds``."""
    unwhitened = chi2 * scales  # vᵀv over the configured variance
    estimate = (unwhitened + prior_dof) / np.maximum(redundancy + prior_dof, 1e-12)
    return np.asarray(np.clip(estimate, bounds[0], bounds[1]), dtype=np.float64)


__all__ = [
    "COMPONENTS",
    "COMPONENT_FIELDS",
    "NoiseEstimate",
    "WalkNoise",
    "chi2_cdf",
    "chi2_quantile",
    "noise_estimate_from_dict",
    "robust_threshold",
    "updated_scales",
]
