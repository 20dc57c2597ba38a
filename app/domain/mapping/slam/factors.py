"""The factors (step 2 of ``slam``): the noise models (:func:`pose_sigmas`,
:func:`odometry_sigmas`, :func:`tag_covariance_in_tag_frame`, :func:`gravity_variances`), the gauge
prior (2a), odometry (2b), gravity (2c) and tags (2d), the problem they make
(:func:`build_problem`) and one walk's share of a joint graph (:func:`chain_graph`)."""

from __future__ import annotations

import math
from typing import Any

import gtsam
import numpy as np
from gtsam.symbol_shorthand import X

from app.domain.frames import FloatArray
from app.domain.mapping.params import SlamParams
from app.domain.upload.session import IntArray

from .inputs import MIN_ODOMETRY_DT_S, WORLD_UP, GraphInputs, to_pose3

#: σ of the gauge prior on the first pose's heading (rad) and position (m).
GAUGE_PRIOR_SIGMA_RAD = 1e-6
GAUGE_PRIOR_SIGMA_M = 1e-6
#: Information of the gauge prior on the first pose's roll and pitch, 1/rad²: next to nothing
#: (gravity measures them, ~1e4 per keyframe), but positive, so the prior's Cholesky exists.
GAUGE_TILT_INFORMATION = 1.0


def pose_sigmas(*, rot_rad: FloatArray | float, trans_m: FloatArray | float) -> FloatArray:
    """Pose3 sigma vector in gtsam's tangent order ``[rot(3) rad, trans(3) m]``."""
    rot = np.broadcast_to(np.asarray(rot_rad, dtype=np.float64), (3,))
    trans = np.broadcast_to(np.asarray(trans_m, dtype=np.float64), (3,))
    return np.concatenate([rot, trans])


def odometry_sigmas(dt_s: float, params: SlamParams) -> FloatArray:
    """Pose3 sigmas of an odometry step spanning ``dt_s`` seconds: variance = rate × dt."""
    dt_s = max(dt_s, MIN_ODOMETRY_DT_S)
    return pose_sigmas(
        rot_rad=math.sqrt(params.odom_angular_var_rad2_per_s * dt_s),
        trans_m=math.sqrt(params.odom_linear_var_m2_per_s * dt_s),
    )


def tag_covariance_in_tag_frame(camera_T_tag: FloatArray, params: SlamParams) -> FloatArray:
    """(6, 6) covariance of a tag detection in the tag frame, ``[rot rad, trans m]``.

    Position: variance ``tag_position_var_m2 · d²`` across the line of sight and
    ``tag_depth_var_ratio`` times that along it (the OpenCV camera's z), d the distance in m.
    Orientation: ``tag_orientation_var_rad2`` about each axis.
    """
    distance_m = float(np.linalg.norm(camera_T_tag[:3, 3]))
    lateral_var_m2 = params.tag_position_var_m2 * max(distance_m, 0.1) ** 2
    camera_cov_m2 = np.diag([1.0, 1.0, params.tag_depth_var_ratio]) * lateral_var_m2
    camera_R_tag = camera_T_tag[:3, :3]
    tag_cov_m2 = camera_R_tag.T @ camera_cov_m2 @ camera_R_tag
    covariance = np.zeros((6, 6))
    covariance[:3, :3] = np.eye(3) * params.tag_orientation_var_rad2
    covariance[3:, 3:] = tag_cov_m2
    return covariance


def gravity_variances(
    offsets_s: FloatArray,
    keyframe_of_pose: IntArray,
    num_keyframes: int,
    params: SlamParams,
    angular_scale: FloatArray,
) -> FloatArray:
    """(K,) the variance of each keyframe's gravity factor, rad², with the gravity of the poses
    it stands for folded in.

    Pose ``j`` between keyframes measures the same up vector as its nearest keyframe ``k`` (both
    come from ARKit's gravity-aligned world, carried to ``k`` by the raw odometry), with the
    odometry's tilt noise over the time between them added: variance ``gravity_var_rad2 +
    angular rate × |t_j − t_k|``. The keyframe's factor holds their combined information
    ``Σ_j 1 / (gravity_var_rad2 + rate · |t_j − t_k|)``; with every pose a keyframe that is one
    factor per pose at ``gravity_var_rad2``, as the paper's graph has.

    offsets_s: (N,) |t_j − t_k| of each pose from the keyframe it is folded into, s.
    keyframe_of_pose: (N,) that keyframe's row in the graph's keyframes. angular_scale: (N,) the
    angular variance factor of each pose's walk.
    """
    rate = params.odom_angular_var_rad2_per_s * angular_scale
    information = 1.0 / (params.gravity_var_rad2 + rate * offsets_s)
    total = np.bincount(
        keyframe_of_pose.astype(np.int64), weights=information, minlength=num_keyframes
    )
    return np.asarray(1.0 / total, dtype=np.float64)


class Problem:
    """The factor graph and its factors by kind (for the residuals)."""

    def __init__(self) -> None:
        self.graph = gtsam.NonlinearFactorGraph()
        self.odometry_factors: list[gtsam.BetweenFactorPose3] = []
        self.gravity_factors: list[gtsam.AttitudeFactorPose3] = []
        self.tag_factors: list[gtsam.BetweenFactorPose3] = []
        self.tag_covariances: list[FloatArray] = []


def build_problem(inputs: GraphInputs, params: SlamParams) -> Problem:
    problem = Problem()
    problem.odometry_factors = build_odometry_factors(inputs, params)
    problem.gravity_factors = build_gravity_factors(inputs, params)
    problem.tag_factors, problem.tag_covariances = build_tag_factors(inputs, params)
    problem.graph = _problem_graph(inputs, problem)
    return problem


def _problem_graph(inputs: GraphInputs, problem: Problem) -> gtsam.NonlinearFactorGraph:
    """The gauge prior, then the problem's odometry, gravity and tag factors, in that order."""
    graph = gtsam.NonlinearFactorGraph()
    graph.add(build_gauge_prior(inputs))
    for kind in (problem.odometry_factors, problem.gravity_factors, problem.tag_factors):
        for factor in kind:
            graph.add(factor)
    return graph


def factor_graph(factors: list[Any]) -> gtsam.NonlinearFactorGraph:
    graph = gtsam.NonlinearFactorGraph()
    for factor in factors:
        graph.add(factor)
    return graph


def build_gauge_prior(inputs: GraphInputs) -> gtsam.PriorFactorPose3:
    """2a. The gauge prior on the first pose: its heading (the turn about the world's up, which
    is ``gauge_up`` in the phone frame) and its position; its roll and pitch are gravity's."""
    return _heading_position_prior(X(0), inputs.gauge_pose, inputs.gauge_up)


def gauge_prior(key: int, world_T_phone: FloatArray) -> gtsam.PriorFactorPose3:
    """The gauge prior of 2a on the pose ``key``, holding it at ``world_T_phone``'s heading and
    position (the world's +y seen from that pose is its up): the one a graph gets when its
    first walk, which held the gauge, is taken out (``mapping/incremental/isam.py``)."""
    return _heading_position_prior(key, to_pose3(world_T_phone), world_T_phone[:3, :3].T @ WORLD_UP)


def _heading_position_prior(
    key: int, pose: gtsam.Pose3, phone_up: FloatArray
) -> gtsam.PriorFactorPose3:
    up = phone_up / np.linalg.norm(phone_up)
    along_up = np.outer(up, up)
    information = np.zeros((6, 6))
    information[:3, :3] = along_up / GAUGE_PRIOR_SIGMA_RAD**2 + GAUGE_TILT_INFORMATION * (
        np.eye(3) - along_up
    )
    information[3:, 3:] = np.eye(3) / GAUGE_PRIOR_SIGMA_M**2
    noise = gtsam.noiseModel.Gaussian.Information(information)
    return gtsam.PriorFactorPose3(key, pose, noise)


def chain_graph(
    inputs: GraphInputs, params: SlamParams, *, key_offset: int = 0, gauge: bool = True
) -> gtsam.NonlinearFactorGraph:
    """The graph :func:`refine` solves for ``inputs`` of one pose chain (a walk), in the same
    order (the gauge prior only with ``gauge``; then odometry, gravity, tags), every phone pose
    ``X(i)`` renamed ``X(key_offset + i)``; landmark keys are kept. A walk's share of a building
    map's joint graph, numbered where the building keeps it (``mapping/incremental/isam.py``):
    for the walk at pose row ``key_offset`` of ``joint.combine_sessions``, factor for factor
    the joint graph's factors of that chain."""
    if inputs.num_chains != 1:
        raise ValueError(f"one pose chain expected, got {inputs.num_chains}")
    problem = build_problem(inputs, params)
    graph = gtsam.NonlinearFactorGraph()
    pose_tag = ord("x")
    for k in range(0 if gauge else 1, int(problem.graph.size())):
        factor = problem.graph.at(k)
        if key_offset:
            keys = factor.keys()  # a gtsam KeyVector
            factor = factor.rekey(
                [key + key_offset if key >> 56 == pose_tag else key for key in keys]
            )
        graph.add(factor)
    return graph


def build_odometry_factors(
    inputs: GraphInputs, params: SlamParams
) -> list[gtsam.BetweenFactorPose3]:
    """2b. Odometry between consecutive keyframes, noise growing with the time between them, plus
    any variance added to the step (``GraphInputs.odometry_added_variance``; one noise model per
    distinct duration, walk and added variance)."""
    noise_by_dt: dict[tuple[float, ...], gtsam.noiseModel.Base] = {}
    factors = []
    keyframes = inputs.keyframes.tolist()
    linear_scale, angular_scale = inputs.odometry_scales()
    added = inputs.odometry_added_variance
    for k, phone_T_next in enumerate(inputs.phone_T_next):
        if not inputs.odometry_linked[k]:
            continue  # the next keyframe starts another pose chain (session)
        key = (
            float(inputs.odometry_dt_s[k]),
            float(linear_scale[k]),
            float(angular_scale[k]),
            float(added[k, 0]),
            float(added[k, 1]),
        )
        noise = noise_by_dt.get(key)
        if noise is None:
            sigmas = odometry_sigmas(key[0], params)
            sigmas[:3] *= math.sqrt(key[2])
            sigmas[3:] *= math.sqrt(key[1])
            if key[3] or key[4]:
                sigmas[:3] = np.sqrt(sigmas[:3] ** 2 + key[4])
                sigmas[3:] = np.sqrt(sigmas[3:] ** 2 + key[3])
            noise = gtsam.noiseModel.Diagonal.Sigmas(sigmas)
            noise_by_dt[key] = noise
        factors.append(
            gtsam.BetweenFactorPose3(X(keyframes[k]), X(keyframes[k + 1]), phone_T_next, noise)
        )
    return factors


def build_gravity_factors(
    inputs: GraphInputs, params: SlamParams
) -> list[gtsam.AttitudeFactorPose3]:
    """2c. Gravity: the measured up direction in the phone frame, held to the map's up, at every
    keyframe, with the gravity of the poses between keyframes folded in
    (:func:`gravity_variances`)."""
    world_up = gtsam.Unit3(WORLD_UP)
    variances = gravity_variances(
        inputs.gravity_offset_s,
        inputs.gravity_keyframe,
        len(inputs.keyframes),
        params,
        inputs.noise_scales[inputs.pose_chain, 1],
    )
    noise_by_variance: dict[float, gtsam.noiseModel.Base] = {}
    factors = []
    for i, phone_up, variance in zip(inputs.keyframes, inputs.phone_up, variances, strict=True):
        noise = noise_by_variance.get(float(variance))
        if noise is None:
            noise = gtsam.noiseModel.Isotropic.Sigma(2, math.sqrt(float(variance)))
            noise_by_variance[float(variance)] = noise
        factors.append(gtsam.AttitudeFactorPose3(X(int(i)), world_up, noise, phone_up))
    return factors


def build_tag_factors(
    inputs: GraphInputs, params: SlamParams
) -> tuple[list[gtsam.BetweenFactorPose3], list[FloatArray]]:
    """2d. Tags, under a Huber kernel; and each factor's covariance (tag frame)."""
    huber = gtsam.noiseModel.mEstimator.Huber.Create(params.huber_k) if params.huber_k > 0 else None
    covariances = _tag_covariances(inputs, params)
    factors = []
    for k, landmark_key in enumerate(inputs.landmark_keys):
        noise: gtsam.noiseModel.Base = gtsam.noiseModel.Gaussian.Covariance(covariances[k])
        if huber is not None:
            noise = gtsam.noiseModel.Robust.Create(huber, noise)
        factors.append(
            gtsam.BetweenFactorPose3(
                X(inputs.tag_pose_indices[k]), landmark_key, inputs.phone_T_tag[k], noise
            )
        )
    return factors, list(covariances)


def _tag_covariances(inputs: GraphInputs, params: SlamParams) -> FloatArray:
    """(U, 6, 6) each tag factor's covariance: :func:`tag_covariance_in_tag_frame` of its
    detection, its blocks scaled by its walk's and its burst's factors (vectorized)."""
    camera_T_tag = inputs.camera_T_tag
    distance_m = np.maximum(np.linalg.norm(camera_T_tag[:, :3, 3], axis=1), 0.1)
    camera_R_tag = camera_T_tag[:, :3, :3]
    along = np.array([1.0, 1.0, params.tag_depth_var_ratio])
    tag_cov = np.einsum("uji,j,ujk->uik", camera_R_tag, along, camera_R_tag)
    position_scale, orientation_scale = inputs.tag_scales()
    covariance = np.zeros((camera_T_tag.shape[0], 6, 6))
    covariance[:, :3, :3] = (
        np.eye(3) * (params.tag_orientation_var_rad2 * orientation_scale)[:, None, None]
    )
    covariance[:, 3:, 3:] = (
        tag_cov * (params.tag_position_var_m2 * distance_m**2 * position_scale)[:, None, None]
    )
    return covariance
