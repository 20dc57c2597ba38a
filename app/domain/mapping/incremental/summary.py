"""One walk condensed to a Gaussian on its tags (a :class:`WalkSummary`), with gtsam.

The walk's own factor graph (``slam.GraphInputs``, ``slam.TrialGraph``: odometry, gravity, its
tag sightings under their Huber kernel, the prior on its first pose's heading and position), with
its own noise (``WalkFit.noise_scales``) held as given, is linearized where its tags are and its
poses fit them best, and the poses are eliminated (gtsam's partial multifrontal elimination: the
Schur complement onto the tags). What is left is the walk's cost as a function of its tags in its
own world frame; where the walk sits in the building is a separate variable (``map_T_world``), so
the summary does not change when the walk is only moved.
"""

from __future__ import annotations

import dataclasses

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X

from app.domain.frames import FloatArray
from app.domain.mapping.keyframes import interpolate_poses
from app.domain.mapping.params import SlamParams
from app.domain.mapping.screening import Screening
from app.domain.mapping.slam import GraphInputs, TrialGraph, values_from
from app.domain.upload.session import Session

from .state import WalkSummary

#: σ of the priors that hold a walk's tags where the building put them while its poses are
#: fitted to them (rad and m): far below any tag's own uncertainty.
HELD_TAG_SIGMA = 1e-7
#: Iterations of that fit at most (it starts from the poses of the last linearization).
HELD_TAG_ITERATIONS = 10


def summarize_walk(
    *,
    walk_id: str,
    fingerprint: str,
    session: Session,
    screening: Screening,
    params: SlamParams,
    noise_scales: FloatArray,
    depth_scale: float,
    world_T_phone: FloatArray,
    world_T_tag: dict[int, FloatArray],
    hold_tags: bool,
    cost_alone: float | None = None,
    relinearized: int = 0,
) -> WalkSummary:
    """The summary of ``session`` (its camera-to-tag distances scaled by ``depth_scale``
    already) at ``world_T_tag`` (its world frame).

    ``hold_tags``: fit the poses to those tags first (from ``world_T_phone``, (N, 4, 4)); else
    ``world_T_phone`` and ``world_T_tag`` are the walk's own optimum already (``WalkFit.alone``).
    ``cost_alone``: its cost at its own optimum (default: the cost here)."""
    fixed = dataclasses.replace(params, estimate_noise=False)
    inputs = GraphInputs(
        session, fixed, screening=screening, noise_scales=np.asarray(noise_scales)[None]
    )
    graph = TrialGraph(inputs).graph(fixed)
    tag_ids = sorted(inputs.tag_rows)
    values = values_from(inputs, world_T_phone[inputs.keyframes], world_T_tag)
    if hold_tags:
        values = _fit_poses_to_tags(graph, values, tag_ids)
    lin = graph.linearize(values)
    poses = gtsam.Ordering()
    for i in inputs.keyframes.tolist():
        poses.push_back(X(i))
    tags = gtsam.Ordering()
    for t in tag_ids:
        tags.push_back(L(t))
    _, remaining = lin.eliminatePartialMultifrontal(poses)
    information, gradient = remaining.hessian(tags)
    world_T_keyframe = np.stack([values.atPose3(X(i)).matrix() for i in inputs.keyframes.tolist()])
    cost = _chain_cost(graph, values, inputs)
    return WalkSummary(
        walk_id=walk_id,
        fingerprint=fingerprint,
        noise_scales=np.array(noise_scales, dtype=np.float64),
        depth_scale=float(depth_scale),
        tag_ids=np.array(tag_ids, dtype=np.int64),
        world_T_tag=np.stack([values.atPose3(L(t)).matrix() for t in tag_ids]),
        information=np.asarray(information, dtype=np.float64),
        gradient=np.asarray(gradient, dtype=np.float64).reshape(-1),
        keyframes=inputs.keyframes.copy(),
        world_T_phone=interpolate_poses(
            session.world_T_phone, session.timestamp_s, inputs.keyframes, world_T_keyframe
        ),
        firmness=_firmness(inputs, tag_ids),
        cost=cost,
        cost_alone=cost if cost_alone is None else float(cost_alone),
        relinearized=relinearized,
    )


def _fit_poses_to_tags(
    graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, tag_ids: list[int]
) -> gtsam.Values:
    """``values`` with the poses that fit its tags best (the tags held by stiff priors, then set
    back exactly where they were)."""
    held = gtsam.NonlinearFactorGraph()
    held.push_back(graph)
    noise = gtsam.noiseModel.Isotropic.Sigma(6, HELD_TAG_SIGMA)
    for t in tag_ids:
        held.add(gtsam.PriorFactorPose3(L(t), values.atPose3(L(t)), noise))
    lm = gtsam.LevenbergMarquardtParams()
    lm.setMaxIterations(HELD_TAG_ITERATIONS)
    lm.setRelativeErrorTol(1e-6)
    lm.setAbsoluteErrorTol(0.0)
    lm.setLinearSolverType("SEQUENTIAL_CHOLESKY")
    solved = gtsam.LevenbergMarquardtOptimizer(held, values, lm).optimize()
    out = gtsam.Values(solved)
    for t in tag_ids:
        out.update(L(t), values.atPose3(L(t)))
    return out


def _chain_cost(
    graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, inputs: GraphInputs
) -> float:
    """The walk's odometry and tag factors' χ² (gravity and the first pose's prior left out), as
    ``slam.chain_costs``: ``TrialGraph`` puts the prior first, then odometry, gravity, tags."""
    odometry = int(np.count_nonzero(inputs.odometry_linked))
    gravity = len(inputs.keyframes)
    total = 0.0
    for k in range(1, graph.size()):
        if 1 + odometry <= k < 1 + odometry + gravity:
            continue
        total += graph.at(k).error(values)
    return 2.0 * total


def _firmness(inputs: GraphInputs, tag_ids: list[int]) -> FloatArray:
    """(n,) Σ over each tag's used sightings of 1 / (position variance factor · distance²)."""
    distance_m = np.maximum(np.linalg.norm(inputs.camera_T_tag[:, :3, 3], axis=1), 0.1)
    position_scale, _ = inputs.tag_scales()
    information = 1.0 / (position_scale * distance_m**2)
    index = {t: k for k, t in enumerate(tag_ids)}
    out = np.zeros(len(tag_ids))
    for tag, value in zip(inputs.tag_ids, information.tolist(), strict=True):
        out[index[tag]] += value
    return out
