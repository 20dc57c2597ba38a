"""Steps 5 and 6: a tag one walk disagrees on gets its own landmark; a walk whose disagreement
its own noise does not explain is down-weighted.

5. *A tag that moved between walks* (re-printed, re-hung) shows as one walk's sightings of it
   disagreeing with the map beyond its noise (mean χ² per sighting above the 99.9% quantile of a
   6-D residual, once divided by the walk's own level of disagreement). The worst such (walk,
   tag) gets a landmark of its own (solved, not a tag of the map), and the map is solved again,
   until none is left (:func:`worst_split`). Of two walks that disagree, the one with the larger
   normalized residual (the looser one) is split off; the map's warnings name it.
6. *A walk whose disagreement its own noise does not explain is down-weighted* (never silently:
   ``SessionPart.weighting`` says why; :func:`weigh_walks`). Joining adds constraints to each
   walk; if its noise were right, its cost would grow by about the redundancy it gains, Δr (a
   shared tag seen by m walks gives 6(m − 1) degrees of freedom, shared by the walks in
   proportion to how loosely each holds it; 4 per extra walk go to placing it). A walk whose cost
   grows by more than χ²(Δr)'s 99% quantile gets all its variances multiplied by
   ``(cost joint − cost alone) / Δr`` (a variance component of its own, estimated in the joint
   map; at least 1, at most ``MAX_DISAGREEMENT_FACTOR``), and the map is solved again.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from app.domain.frames import FloatArray
from app.domain.mapping.joint.model import BoolArray
from app.domain.mapping.joint.plan import JointInputs
from app.domain.mapping.noise import chi2_quantile
from app.domain.mapping.params import SlamParams
from app.domain.mapping.slam import GraphInputs, Solution, chain_costs, solution_residuals

#: Largest factor by which a walk's variances are raised when it disagrees with the others.
MAX_DISAGREEMENT_FACTOR = 100.0


#: A walk is down-weighted only when its cost grew by more than this quantile of χ²(Δr) allows.
DISAGREEMENT_QUANTILE = 0.99


#: A walk's sightings of a shared tag whose mean χ² per sighting is above this quantile of a 6-D
#: residual's get a landmark of their own.
SPLIT_QUANTILE = 0.999


#: Degrees of freedom of placing one more walk: a turn about +y and a translation.
PLACEMENT_DOF = 4.0


#: A change of a walk's disagreement factor smaller than this fraction is not worth a round.
DISAGREEMENT_TOLERANCE = 0.05


@dataclass(frozen=True, slots=True, kw_only=True)
class Weighing:
    """Step 4's figures per walk: the factors it implies, the walk's cost in the joint map with
    its own noise, its excess over its cost alone, and the redundancy joining gave it."""

    factors: FloatArray
    cost_joint: FloatArray
    excess: FloatArray
    gain: FloatArray
    significant: BoolArray


def weigh_walks(
    joint: JointInputs,
    inputs: GraphInputs,
    params: SlamParams,
    solution: Solution,
    disagreement: FloatArray,
    splits: frozenset[tuple[int, int]],
) -> Weighing:
    """Each walk's disagreement factor at ``solution`` (step 6, the module docstring): its
    cost with its own noise, less its cost alone, over the redundancy it gained; 1 unless that
    excess is beyond ``DISAGREEMENT_QUANTILE`` of χ²(Δr)."""
    scales = inputs.noise_scales
    inputs.noise_scales = joint.base_scales
    try:
        cost_joint = chain_costs(inputs, params, solution.values)
    finally:
        inputs.noise_scales = scales
    cost_alone = joint.cost_alone
    gain = _redundancy_gain(joint, inputs, disagreement, splits)
    excess = cost_joint - cost_alone
    limit = np.array([chi2_quantile(DISAGREEMENT_QUANTILE, max(1, round(g))) for g in gain])
    significant = excess > limit
    factors = np.where(
        significant, np.clip(excess / gain, 1.0, MAX_DISAGREEMENT_FACTOR), 1.0
    ).astype(np.float64)
    return Weighing(
        factors=factors, cost_joint=cost_joint, excess=excess, gain=gain, significant=significant
    )


def _redundancy_gain(
    joint: JointInputs,
    inputs: GraphInputs,
    disagreement: FloatArray,
    splits: frozenset[tuple[int, int]],
) -> FloatArray:
    """(S,) Δr of each walk: every shared tag's 6(m − 1) degrees of freedom, each walk taking
    the share ``1 − w / Σw`` (w: how firmly it holds the tag, the information of its sightings'
    positions), less ``PLACEMENT_DOF`` × (S − 1) / S for placing it; at least 1."""
    S = len(joint.plan.datasets)
    detections = joint.combined.detections
    rows = np.array(inputs.tag_detection_rows, dtype=np.int64)
    chain = inputs.detection_chain
    distance_m = np.maximum(np.linalg.norm(detections.camera_T_tag[rows, :3, 3], axis=1), 0.1)
    position_scale, _ = inputs.tag_scales()
    information = 1.0 / (position_scale * distance_m**2)
    tags = detections.tag_id[rows]
    firmness: dict[int, np.ndarray] = {}
    for k, (t, s) in enumerate(zip(tags.tolist(), chain.tolist(), strict=True)):
        if (s, t) in splits:
            continue
        firmness.setdefault(t, np.zeros(S))[s] += information[k]
    gain = np.full(S, -PLACEMENT_DOF * (S - 1) / S)
    for w in firmness.values():
        if np.count_nonzero(w) >= 2:
            gain += np.where(w > 0, 6.0 * (1.0 - w / w.sum()), 0.0)
    del disagreement  # the scales in ``inputs`` carry it
    return np.asarray(np.maximum(gain, 1.0), dtype=np.float64)


def factors_changed(new: FloatArray, old: FloatArray) -> bool:
    return bool(np.max(np.abs(np.log(new / old))) > math.log1p(DISAGREEMENT_TOLERANCE))


def worst_split(
    joint: JointInputs,
    inputs: GraphInputs,
    solution: Solution,
    splits: frozenset[tuple[int, int]],
) -> tuple[tuple[int, int], float] | None:
    """The (walk, tag) whose sightings of a tag other walks saw too disagree most with the map,
    with its mean χ² per sighting, if that is beyond ``SPLIT_QUANTILE`` of a 6-D residual's once
    divided by the walk's own level of disagreement (the median over its shared tags, against
    the χ²'s median, when it has at least 3; step 5)."""
    residuals = solution_residuals(inputs, solution)
    detections = joint.combined.detections
    tags = detections.tag_id[residuals.tag_detection_index]
    chain = inputs.detection_chain
    chi2: dict[tuple[int, int], list[float]] = {}
    for t, s, c in zip(tags.tolist(), chain.tolist(), residuals.tag_chi2.tolist(), strict=True):
        if (s, t) not in splits:
            chi2.setdefault((s, t), []).append(c)
    walks_of: dict[int, int] = {}
    for _, t in chi2:
        walks_of[t] = walks_of.get(t, 0) + 1
    limit = chi2_quantile(SPLIT_QUANTILE, 6)
    typical = chi2_quantile(0.5, 6)
    mean = {st: float(np.mean(values)) for st, values in chi2.items() if walks_of[st[1]] >= 2}
    # each walk's own level of disagreement (the median of its shared tags'): a walk whose noise
    # is underestimated everywhere is step 6's business, not a reason to split all its tags
    level = {}
    for w in {st[0] for st in mean}:
        of_walk = [c for (s, _), c in mean.items() if s == w]
        level[w] = max(1.0, float(np.median(of_walk)) / typical) if len(of_walk) >= 3 else 1.0
    candidates = [
        (c / level[s], joint.plan.datasets[s], t, s)
        for (s, t), c in mean.items()
        if c / level[s] > limit
    ]
    if not candidates:
        return None
    _, _, t, s = max(candidates)
    return (s, t), mean[s, t]
