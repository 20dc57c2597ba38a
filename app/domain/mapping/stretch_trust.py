"""Odometry trusted stretch by stretch (issue 37, item 4): a prototype, not wired in.

    loose = {"oblique_209_occam": [(105, 132)]}            # pose rows of that walk's stretches
    tags = resolve_with_loose_stretches(joint, loose, variance_factor=100.0)

A building map trusts each walk's odometry the same along its whole length (its variance a rate
× time). Real walks err in a few stretches (the stairs); this module re-solves a building map
with the odometry variance of chosen stretches multiplied (their σ × √factor), from the map's
own optimum, everything else as the map had it (each walk's noise and weight), so that a rule
that picks the stretches can be measured against the truth. Which stretches to loosen is the open
question: bench/regions.py (table 2b) shows what the real pair would gain if a rule knew.

Kept apart from the mapping code on purpose: it rebuilds the joint graph from the map's combined
session (screened again, no split landmarks), so it is a measuring tool.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence

import numpy as np

from app.domain.frames import FloatArray
from app.domain.mapping.joint import JointMap
from app.domain.mapping.joint.stairs import stairs_variance
from app.domain.mapping.params import SlamParams
from app.domain.mapping.slam import GraphInputs, refine, solved_poses, values_from


def resolve_with_loose_stretches(
    joint: JointMap,
    loose: Mapping[str, Sequence[tuple[int, int]]],
    *,
    variance_factor: float,
    params: SlamParams | None = None,
) -> dict[int, FloatArray]:
    """The tags of ``joint`` solved again with the odometry variance × ``variance_factor`` on
    each walk's stretches in ``loose`` (walk name → (first pose row, last pose row) of the walk's
    own session, end exclusive), from ``joint``'s optimum; each walk keeps its noise, weight and
    stairs' variance (``params``'). With no stretch loosened it is the map's graph solved again
    (a baseline to compare with)."""
    params = params or SlamParams()
    fixed = dataclasses.replace(params, estimate_noise=False)
    scale = np.ones(joint.combined.num_poses)
    for part in joint.parts:
        for first, stop in loose.get(part.dataset, ()):
            scale[part.pose_rows.start + first : part.pose_rows.start + stop] = variance_factor
    inputs = GraphInputs(
        joint.combined,
        fixed,
        chain_starts=[part.pose_rows.start for part in joint.parts],
        noise_scales=np.stack([part.noise_scales for part in joint.parts]),
        odometry_variance_scale=scale,
        odometry_added_variance=np.concatenate(
            [stairs_variance(session, params) for session in joint.sessions]
        ),
    )
    start = values_from(inputs, joint.map.world_T_phone[inputs.keyframes], joint.map.tag_poses())
    solution = refine(inputs, fixed, start)
    _, world_T_tag, _ = solved_poses(inputs, solution.values)
    return world_T_tag
