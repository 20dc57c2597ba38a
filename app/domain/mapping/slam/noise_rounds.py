"""The noise estimate's rounds (step 4 of ``slam``, with ``estimate_noise``): iterated
variance-component estimation of each walk's odometry and tag variances
(:func:`estimate_noise_scales`; the update rule is ``noise.py``'s), each round's residuals and
redundancies (:func:`_component_statistics`) from the hat blocks of the factors
(:func:`_factor_hats`, :class:`_ChainCovariance`)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Any

import gtsam
import numpy as np
from gtsam.symbol_shorthand import X

from app.domain.frames import FloatArray
from app.domain.mapping.noise import COMPONENTS, NoiseEstimate, updated_scales
from app.domain.mapping.params import SlamParams

from .factors import Problem, build_problem
from .inputs import GraphInputs, landmark_keys_of
from .optimizer import IterationCallback, counting_from, levenberg_marquardt

#: Most optimizations one noise estimate may take (each one LM solve and one pass over the
#: factors' marginal covariances).
MAX_NOISE_ROUNDS = 12
#: The estimate has converged when no variance changed by more than this fraction in a round.
NOISE_TOLERANCE = 0.05
#: The rounds of a noise estimate before its last stop LM at steps this many times larger, or
#: after this many iterations (a walk whose odometry fits badly crawls for dozens; the residuals
#: a round reads barely change meanwhile).
ROUGH_STEP_FACTOR = 100.0
ROUGH_MAX_ITERATIONS = 6
#: Largest keyframe–landmark block a noise estimate holds, entries (8 bytes each, five arrays
#: of it at the peak: 200 MB); beyond it (a 40,000-pose walk with 59 tags: 12.7 million, 760 MB
#: and 12 s) the configured variances are used, and the map says so.
MAX_NOISE_ESTIMATE_ENTRIES = 5_000_000
#: No variance is estimated more than this factor away from the configured one (either way).
NOISE_SCALE_BOUNDS = (1e-4, 1e4)


def estimate_noise_scales(
    inputs: GraphInputs,
    params: SlamParams,
    start: gtsam.Values,
    chains: Sequence[int],
    on_iteration: IterationCallback | None,
    ordering: gtsam.Ordering,
) -> tuple[gtsam.Values, int, tuple[NoiseEstimate, ...]]:
    """Iterated variance-component estimation of ``chains``' noise (``noise.py``): optimize,
    read each component's residuals and redundancy, rescale, repeat until no scale changes by
    more than ``NOISE_TOLERANCE``; then optimize with the final scales. Sets
    ``inputs.noise_scales``. Returns the solution, LM's iterations (all rounds) and one estimate
    per chain of ``inputs`` (the chains not estimated: their given scales, 0 rounds)."""
    selected = np.zeros(inputs.num_chains, dtype=bool)
    selected[list(chains)] = True
    values, iterations = start, 0
    rounds, converged, note = 0, False, ""
    chi2 = redundancy = rows = np.full((inputs.num_chains, len(COMPONENTS)), np.nan)
    previous_step: FloatArray | None = None
    # the rounds before the last need the optimum to within centimetres, not its last 0.1 mm
    rough = dataclasses.replace(
        params,
        converged_step_m=params.converged_step_m * ROUGH_STEP_FACTOR,
        converged_step_rad=params.converged_step_rad * ROUGH_STEP_FACTOR,
        max_iterations=min(params.max_iterations, ROUGH_MAX_ITERATIONS),
    )
    while True:
        last = converged or not selected.any() or rounds + 1 > MAX_NOISE_ROUNDS
        problem = build_problem(inputs, params)
        values, done, _ = levenberg_marquardt(
            problem.graph,
            values,
            params if last else rough,
            counting_from(iterations, on_iteration),
            ordering=ordering,
        )
        iterations += done
        rounds += 1
        if last:
            break
        try:
            chi2, redundancy, rows = _component_statistics(inputs, problem, values)
        except RuntimeError as err:  # indeterminate: keep the last scales
            note = f"stopped after {rounds} rounds: the system became indeterminate ({_first(err)})"
            break
        scales = inputs.noise_scales.copy()
        new = updated_scales(
            scales[selected],
            chi2[selected],
            redundancy[selected],
            prior_dof=params.noise_prior_dof,
            bounds=NOISE_SCALE_BOUNDS,
        )
        step = np.log(new / scales[selected])
        change = float(np.max(np.abs(step)))
        converged = change <= math.log1p(NOISE_TOLERANCE)
        if previous_step is not None and not converged:
            new = np.exp(np.log(new) + _aitken_tail(previous_step, step))
            previous_step = None  # extrapolate from fresh steps only
        else:
            previous_step = step
        scales[selected] = new
        inputs.noise_scales = scales
    if not converged and not note and selected.any():
        note = f"not converged after {MAX_NOISE_ROUNDS} rounds; the last variances are used"
    if not selected.any():
        note = (
            f"not estimated: {len(inputs.keyframes)} keyframes × {len(landmark_keys_of(inputs))} "
            f"landmarks is beyond what the estimate holds in memory "
            f"({MAX_NOISE_ESTIMATE_ENTRIES:.0e} entries); the configured variances are used"
        )
    estimates = []
    for c in range(inputs.num_chains):
        with np.errstate(invalid="ignore", divide="ignore"):
            per_redundancy = chi2[c] / redundancy[c]
        estimates.append(
            NoiseEstimate(
                scales=inputs.noise_scales[c].copy(),
                redundancy=redundancy[c].copy(),
                rows=rows[c].copy(),
                chi2_per_redundancy=np.where(redundancy[c] > 0, per_redundancy, np.nan),
                rounds=rounds if selected[c] else 0,
                converged=bool(converged and selected[c]),
                note=note,
            )
        )
    return values, iterations, tuple(estimates)


def estimate_size(inputs: GraphInputs) -> int:
    """Entries of the keyframe–landmark covariance the estimate holds (:class:`_ChainCovariance`:
    K × 6 × 6T), for a graph of one pose chain (a walk); 0 for a building's several chains."""
    if inputs.num_chains != 1:
        return 0
    return len(inputs.keyframes) * 36 * len(landmark_keys_of(inputs))


def _aitken_tail(previous: FloatArray, step: FloatArray) -> FloatArray:
    """What is left of an oscillating sequence after its last ``step`` (log-scales), from the
    ratio of its last two steps: ``step · r / (1 − r)`` where the ratio is within (−0.9, 0)
    (Aitken's Δ²: the odometry's yaw component oscillates, ratio ≈ −0.5, and settles rounds
    sooner), 0 elsewhere (a monotone sequence's first steps, from far, are not geometric yet:
    extrapolating them overshoots)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.where(previous != 0, step / previous, 0.0)
    usable = (ratio > -0.9) & (ratio < 0.0)
    return np.asarray(np.where(usable, step * ratio / (1.0 - np.where(usable, ratio, 0.0)), 0.0))


def _component_statistics(
    inputs: GraphInputs, problem: Problem, values: gtsam.Values
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """(S, 4) each chain's whitened squared residuals ``vᵀPv``, redundancy ``Σ (1 − h_ii)`` and
    rows, per component (``noise.COMPONENTS``), at ``values``. The hat matrix's block of a factor
    is ``A Σ Aᵀ``, ``A`` its whitened (robust-weighted) Jacobian and ``Σ`` the joint marginal
    covariance of its variables (:func:`_factor_covariances`). The odometry's rotation counts about
    the world's up only (its yaw, along the phone-frame up vector ``u``: ``(uᵀ e)²`` and
    ``1 − uᵀ H u``): its tilt is gravity's."""
    shape = (inputs.num_chains, len(COMPONENTS))
    chi2, redundancy, rows = np.zeros(shape), np.zeros(shape), np.zeros(shape)
    odometry, tags = _factor_hats(inputs, problem, values)
    linked = np.flatnonzero(inputs.odometry_linked)
    chain = inputs.keyframe_chain[linked]
    H, b = odometry
    u = inputs.phone_up_xyz[linked]
    np.add.at(chi2[:, 0], chain, np.einsum("fi,fi->f", b[:, 3:], b[:, 3:]))
    np.add.at(redundancy[:, 0], chain, 3.0 - np.einsum("fii->f", H[:, 3:, 3:]))
    np.add.at(chi2[:, 1], chain, np.einsum("fi,fi->f", u, b[:, :3]) ** 2)
    np.add.at(redundancy[:, 1], chain, 1.0 - np.einsum("fi,fij,fj->f", u, H[:, :3, :3], u))
    np.add.at(rows[:, 0], chain, 3.0)
    np.add.at(rows[:, 1], chain, 1.0)
    H, b = tags
    chain = inputs.detection_chain
    np.add.at(chi2[:, 3], chain, np.einsum("fi,fi->f", b[:, :3], b[:, :3]))
    np.add.at(redundancy[:, 3], chain, 3.0 - np.einsum("fii->f", H[:, :3, :3]))
    np.add.at(chi2[:, 2], chain, np.einsum("fi,fi->f", b[:, 3:], b[:, 3:]))
    np.add.at(redundancy[:, 2], chain, 3.0 - np.einsum("fii->f", H[:, 3:, 3:]))
    np.add.at(rows[:, 2], chain, 3.0)
    np.add.at(rows[:, 3], chain, 3.0)
    return chi2, np.maximum(redundancy, 0.0), rows


Hats = tuple[FloatArray, FloatArray]


def _factor_hats(inputs: GraphInputs, problem: Problem, values: gtsam.Values) -> tuple[Hats, Hats]:
    """The hat blocks ``A Σ Aᵀ`` ((F, 6, 6)) and whitened residuals ``b`` ((F, 6)) of the odometry
    factors and of the tag factors, at ``values``.

    A graph of one pose chain (one walk: where the noise is estimated) has a structure that gives
    every block needed in O(K) (:class:`_ChainCovariance`); any other graph asks gtsam's
    ``Marginals`` factor by factor (some 10–100 times slower)."""
    odometry = [f.linearize(values) for f in problem.odometry_factors]
    tags = [f.linearize(values) for f in problem.tag_factors]
    if inputs.num_chains == 1 and len(inputs.keyframes) >= 2:
        covariance = _ChainCovariance(inputs, problem, values, odometry, tags)
        return covariance.hats(odometry), covariance.hats(tags)
    marginals = gtsam.Marginals(problem.graph, values)

    def hats(linear: list[Any]) -> Hats:
        H, b = np.zeros((len(linear), 6, 6)), np.zeros((len(linear), 6))
        for k, factor in enumerate(linear):
            A, b[k] = factor.jacobian()
            keys = gtsam.KeyVector(factor.keys())
            H[k] = A @ marginals.jointMarginalCovariance(keys).fullMatrix() @ A.T
        return H, b

    return hats(odometry), hats(tags)


class _ChainCovariance:
    """The blocks of the posterior covariance ``N⁻¹`` that the factors of a one-chain graph
    touch, from its whitened Jacobians at the solution.

    Order the variables as the keyframes (in time), then the landmarks: ``N = [[P, B], [Bᵀ, C]]``,
    ``P`` block-tridiagonal (odometry joins consecutive keyframes only; gravity, the gauge and the
    sightings add to its diagonal), ``C`` block-diagonal, ``B`` a keyframe's sightings. With
    ``Y = P⁻¹B`` (block-tridiagonal solve) and the landmarks' Schur complement ``S = C − BᵀY``:
    ``Σ_ll = S⁻¹``, ``Σ_xl = −Y S⁻¹`` and ``Σ_xx = P⁻¹ + Y S⁻¹ Yᵀ``. ``P⁻¹``'s diagonal and first
    off-diagonal blocks come from a forward elimination ``F_k = P_kk − E_{k−1}ᵀ F_{k−1}⁻¹ E_{k−1}``
    and the backward pass ``G_kk = F_k⁻¹ + F_k⁻¹ E_k G_{k+1,k+1} E_kᵀ F_k⁻¹``,
    ``G_{k,k+1} = −F_k⁻¹ E_k G_{k+1,k+1}`` (``E_k = P_{k,k+1}``)."""

    def __init__(
        self,
        inputs: GraphInputs,
        problem: Problem,
        values: gtsam.Values,
        odometry: list[Any],
        tags: list[Any],
    ) -> None:
        K = len(inputs.keyframes)
        self.row = {int(X(i)): k for k, i in enumerate(inputs.keyframes.tolist())}
        self.column = {key: t for t, key in enumerate(landmark_keys_of(inputs))}
        T = len(self.column)
        D, E = np.zeros((K, 6, 6)), np.zeros((K - 1, 6, 6))
        C, B = np.zeros((T, 6, 6)), np.zeros((K, T, 6, 6))
        prior, _ = problem.graph.at(0).linearize(values).jacobian()
        D[0] += prior.T @ prior
        gravity = np.stack([f.linearize(values).jacobian()[0] for f in problem.gravity_factors])
        D += np.swapaxes(gravity, 1, 2) @ gravity
        if odometry:
            A = np.stack([f.jacobian()[0] for f in odometry])
            first = np.array([self.row[f.keys()[0]] for f in odometry])
            At = np.swapaxes(A, 1, 2)
            information = At @ A
            np.add.at(D, first, information[:, :6, :6])
            np.add.at(D, first + 1, information[:, 6:, 6:])
            np.add.at(E, first, information[:, :6, 6:])
        if tags:
            A = np.stack([f.jacobian()[0] for f in tags])
            keyframe = np.array([self.row[f.keys()[0]] for f in tags])
            landmark = np.array([self.column[f.keys()[1]] for f in tags])
            information = np.swapaxes(A, 1, 2) @ A
            np.add.at(D, keyframe, information[:, :6, :6])
            np.add.at(C, landmark, information[:, 6:, 6:])
            np.add.at(B, (keyframe, landmark), information[:, :6, 6:])
        B6 = np.swapaxes(B, 1, 2).reshape(K, 6, 6 * T)
        # forward elimination (P's block LDLᵀ), with B's columns carried along: Y = P⁻¹ B
        forward_inv = np.empty_like(D)
        carried = np.empty_like(B6)
        pivot = D[0]
        carried[0] = B6[0]
        for k in range(K):
            if k:
                pivot = D[k] - E[k - 1].T @ forward_inv[k - 1] @ E[k - 1]
                carried[k] = B6[k] - E[k - 1].T @ (forward_inv[k - 1] @ carried[k - 1])
            forward_inv[k] = np.linalg.inv(pivot)
        p_diagonal, p_next = np.empty_like(D), np.empty_like(E)
        Y = np.empty_like(B6)
        p_diagonal[K - 1] = forward_inv[K - 1]
        Y[K - 1] = forward_inv[K - 1] @ carried[K - 1]
        for k in range(K - 2, -1, -1):
            back = forward_inv[k] @ E[k]
            p_next[k] = -back @ p_diagonal[k + 1]
            p_diagonal[k] = forward_inv[k] - p_next[k] @ back.T
            Y[k] = forward_inv[k] @ carried[k] - back @ Y[k + 1]
        schur = -(B6.reshape(6 * K, 6 * T).T @ Y.reshape(6 * K, 6 * T))
        for t in range(T):
            schur[6 * t : 6 * t + 6, 6 * t : 6 * t + 6] += C[t]
        covariance_l = np.asarray(np.linalg.inv(schur) if T else np.zeros((0, 0)), np.float64)
        #: (T, 6, 6) each landmark's covariance; (K, 6, 6T) −(keyframe–landmark covariance)
        self.landmark_blocks = (
            np.stack([covariance_l[6 * t : 6 * t + 6, 6 * t : 6 * t + 6] for t in range(T)])
            if T
            else np.zeros((0, 6, 6))
        )
        # one large product rather than K small ones (BLAS runs it an order faster)
        self.W = (Y.reshape(6 * K, 6 * T) @ covariance_l).reshape(K, 6, 6 * T)
        #: (K, 6, 6) and (K−1, 6, 6): Σ_xx's diagonal and first off-diagonal blocks
        self.diagonal = p_diagonal + np.einsum("kiu,kju->kij", self.W, Y)
        self.next = p_next + np.einsum("kiu,kju->kij", self.W[:-1], Y[1:])

    def hats(self, linear: list[Any]) -> Hats:
        """The hat blocks and whitened residuals of ``linear``'s factors (each on two
        consecutive keyframes, or on a keyframe and a landmark)."""
        F = len(linear)
        A, b = np.zeros((F, 6, 12)), np.zeros((F, 6))
        covariance = np.zeros((F, 12, 12))
        for f, factor in enumerate(linear):
            A[f], b[f] = factor.jacobian()
            first, second = factor.keys()
            i = self.row[first]
            covariance[f, :6, :6] = self.diagonal[i]
            if second in self.row:  # the next keyframe
                covariance[f, :6, 6:] = self.next[i]
                covariance[f, 6:, 6:] = self.diagonal[i + 1]
            else:
                t = self.column[second]
                covariance[f, :6, 6:] = -self.W[i, :, 6 * t : 6 * t + 6]
                covariance[f, 6:, 6:] = self.landmark_blocks[t]
            covariance[f, 6:, :6] = covariance[f, :6, 6:].T
        return A @ covariance @ np.swapaxes(A, 1, 2), b


def _first(err: BaseException) -> str:
    text = str(err).strip()
    return text.splitlines()[0] if text else type(err).__name__
