"""An ISAM2 building map's state made from a batch build's optimum (issue 38), so that the next
add after a batch build is incremental.

    state, why_not = state_from_batch(joint, walks, params)   # state None: why_not says why

No solve: each walk's graph is fixed by its session and its fit (``JointMap.parts[s].fit``: the
depth scale, noise scales and cost alone the batch build used), its keyframes by its session and
the parameters (``GraphInputs``, as ``IsamBuilding.restore`` computes them again), and the
estimate to linearize at is the batch's optimum (its poses at those keyframes, its tags). Keyed
as ``IsamBuilding.build`` keys the walks (each from the poses of the walks before it), so that
``IsamBuilding.restore`` of it makes the tree ``build`` would have made, at the batch optimum.

Only where the batch graph is the tree's graph (step 4 as it is): a batch build that rescaled a
walk's odometry (step 3), set a tag apart (step 5), down-weighted a walk (step 6), added its
stairs' variance (the stairs rule) or used the variances as given makes no state, since the tree
would hold another graph than the one the map was solved on.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from app.domain.mapping.joint import JointMap, scaled_tag_depths
from app.domain.mapping.joint.stairs import stairs_on
from app.domain.mapping.params import SlamParams
from app.domain.mapping.screening import screen_detections
from app.domain.mapping.slam import GraphInputs

from .isam_state import IsamState, IsamWalkState
from .state import Walk, walk_fingerprint

#: How far a walk's noise scales in the map may be from its own (step 6 left it as it is).
SAME_SCALES_RTOL = 1e-9


def why_not_incremental(joint: JointMap, params: SlamParams) -> str | None:
    """Why the batch map ``joint`` is not the optimum of the tree's graph (None: it is)."""
    if len(joint.parts) < 2:
        return "a map of one walk"
    if not params.estimate_noise:
        return "the variances as given (no noise estimate)"
    if stairs_on(params):
        return "the stairs rule adds variance the tree's graph does not"
    for part in joint.parts:
        if part.fit is None:
            return f"{part.dataset}: no fit of its own"
        if part.alignment.odometry_scale != 1.0:
            return f"{part.dataset}: its odometry rescaled ×{part.alignment.odometry_scale:.3f}"
        if part.local_tags:
            return f"{part.dataset}: tags {list(part.local_tags)} set apart"
        if part.disagreement_factor != 1.0 or not np.allclose(
            part.noise_scales, part.fit.noise_scales, rtol=SAME_SCALES_RTOL, atol=0.0
        ):
            return f"{part.dataset}: down-weighted ×{part.disagreement_factor:.2f}"
    return None


def state_from_batch(
    joint: JointMap, walks: Sequence[Walk], params: SlamParams
) -> tuple[IsamState | None, str]:
    """The state ``IsamBuilding.state()`` would give after ``IsamBuilding.build(walks, params)``
    settled at ``joint``'s optimum; ``walks``: the batch build's sessions as given (its names,
    in its order). ``(None, why)`` where the batch graph is not the tree's
    (:func:`why_not_incremental`, or a walk's tags other than the map's)."""
    if [w.walk_id for w in walks] != [p.dataset for p in joint.parts]:
        raise ValueError("state_from_batch: the walks are not the batch build's, in its order")
    why = why_not_incremental(joint, params)
    if why is not None:
        return None, why
    fixed = dataclasses.replace(params, estimate_noise=False)
    states: list[IsamWalkState] = []
    graph_tags: set[int] = set()
    next_key = 0
    for walk, part in zip(walks, joint.parts, strict=True):
        fit = part.fit
        assert fit is not None  # why_not_incremental
        session = scaled_tag_depths(walk.session, fit.tag_depth_scale)
        inputs = GraphInputs(
            session,
            fixed,
            screening=screen_detections(walk.session.detections, params),
            noise_scales=np.asarray(fit.noise_scales, dtype=np.float64)[None, :],
        )
        graph_tags.update(inputs.tag_rows)
        map_T_phone = joint.map.world_T_phone[part.pose_rows]
        alone_tag_ids = np.asarray(fit.alone.tag_ids, dtype=np.int64)
        states.append(
            IsamWalkState(
                walk_id=walk.walk_id,
                fingerprint=walk_fingerprint(walk.session),
                depth_scale=float(fit.tag_depth_scale),
                noise_scales=np.array(fit.noise_scales, dtype=np.float64),
                cost_alone=float(fit.cost),
                key_offset=next_key,
                map_T_world=np.array(part.alignment.map_T_world, dtype=np.float64),
                keyframes=np.asarray(inputs.keyframes, dtype=np.int64),
                map_T_keyframe=np.array(map_T_phone[inputs.keyframes], dtype=np.float64),
                alone_tag_ids=alone_tag_ids,
                world_T_tag_alone=np.array(fit.alone.world_T_tag, dtype=np.float64).reshape(
                    len(alone_tag_ids), 4, 4
                ),
            )
        )
        next_key += session.num_poses
    tag_ids = np.asarray(joint.map.tag_ids, dtype=np.int64)
    if graph_tags != set(tag_ids.tolist()):
        return None, (
            f"the walks' graphs hold tags {sorted(graph_tags)}, the map {sorted(tag_ids.tolist())}"
        )
    return (
        IsamState(
            walks=tuple(states),
            tag_ids=tag_ids,
            map_T_tag=np.array(joint.map.world_T_tag, dtype=np.float64),
            params=params.to_dict(),
            next_key=next_key,
        ),
        "",
    )


__all__ = ["state_from_batch", "why_not_incremental"]
