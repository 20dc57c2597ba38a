"""The building problem: the tags and the walks' placements under the walks' summaries.

Variables: every tag's pose in the map (``map_T_tag``, 6 degrees of freedom) and every walk's
placement but the first's (``map_T_world``: a turn about +y and a translation, 4; both frames are
gravity-aligned, and the walk's gravity is inside its summary). Walk ``s`` costs
``½ δᵀ H δ − g · δ`` with ``δ_i = Log(world_T_tag_i⁻¹ · map_T_world⁻¹ · map_T_tag_i)`` over its
tags (:class:`WalkSummary`). Solved by Levenberg–Marquardt on the dense normal equations
(6 T + 4 (S − 1) unknowns: about 1,400 for 200 walks of a building of 100 tags).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from app.domain.frames import FloatArray, se3_inverse, skew, so3_exp, so3_log

from .state import IntArray, WalkSummary

#: The placement's degrees of freedom among a pose's tangent ``[rot(3), trans(3)]``: the turn
#: about +y and the translation.
PLACEMENT_AXES = (1, 3, 4, 5)
#: The building is solved when no tag or placement moves by more than this in an iteration (m,
#: rad): the batch build's own tolerance (``SlamParams.converged_step_m``, ``_rad``).
CONVERGED_STEP_M = 1e-4
CONVERGED_STEP_RAD = 1e-5
#: Iterations of the building solve at most.
MAX_ITERATIONS = 50


@dataclass(frozen=True, slots=True, kw_only=True)
class BuildingSolution:
    """The solved building: placements (S, 4, 4), tags (T, 4, 4) in ``tag_ids`` order, each
    walk's tags' offsets from its linearization point (``offsets[s]``: (n_s, 6)), its cost (χ²,
    from its summary), and the iterations taken."""

    map_T_world: FloatArray
    map_T_tag: FloatArray
    offsets: tuple[FloatArray, ...]
    walk_costs: FloatArray
    iterations: int


def solve_building(
    walks: Sequence[WalkSummary],
    map_T_world: FloatArray,
    tag_ids: IntArray,
    map_T_tag: FloatArray,
) -> BuildingSolution:
    """Levenberg–Marquardt from ``map_T_world`` ((S, 4, 4); the first held) and ``map_T_tag``
    ((T, 4, 4), ``tag_ids`` sorted)."""
    problem = _Problem(walks, tag_ids)
    placements = np.array(map_T_world, dtype=np.float64)
    tags = np.array(map_T_tag, dtype=np.float64)
    damping = 1e-9
    cost, hessian, gradient = problem.normal_equations(placements, tags)
    iterations = 0
    while iterations < MAX_ITERATIONS:
        iterations += 1
        diagonal = np.maximum(np.diag(hessian), 1e-9)
        while True:
            step = _solve(hessian + damping * np.diag(diagonal), -gradient)
            new_tags, new_placements = problem.retracted(tags, placements, step)
            new_cost, new_hessian, new_gradient = problem.normal_equations(new_placements, new_tags)
            if new_cost <= cost + 1e-12 * abs(cost) or damping > 1e8:
                break
            damping *= 10.0
        damping = max(damping / 10.0, 1e-9)
        tags, placements = new_tags, new_placements
        cost, hessian, gradient = new_cost, new_hessian, new_gradient
        step_m, step_rad = problem.largest_step(step)
        if step_m <= CONVERGED_STEP_M and step_rad <= CONVERGED_STEP_RAD:
            break
    delta = problem.offsets(placements, tags)[0]
    offsets = tuple(delta[pairs] for pairs in problem.pairs)
    costs = np.array(
        [
            walk.cost
            + float(d.reshape(-1) @ walk.information @ d.reshape(-1))
            - 2.0 * float(walk.gradient @ d.reshape(-1))
            for walk, d in zip(walks, offsets, strict=True)
        ]
    )
    return BuildingSolution(
        map_T_world=placements,
        map_T_tag=tags,
        offsets=offsets,
        walk_costs=costs,
        iterations=iterations,
    )


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class _Group:
    """Walks with the same number of tags: their pairs (G, n), summaries' information
    (G, 6n, 6n) and gradients (G, 6n), and their columns in the normal equations (G, 6n + 4)."""

    pairs: IntArray
    information: FloatArray
    gradient: FloatArray
    columns: IntArray


class _Problem:
    """The building's (walk, tag) pairs, flattened: pair ``k`` is tag ``tag_row[k]`` of walk
    ``walk_row[k]``, linearized at ``lin_T_world[k]``'s inverse (``world_T_tag``)."""

    def __init__(self, walks: Sequence[WalkSummary], tag_ids: IntArray) -> None:
        index = {int(t): k for k, t in enumerate(tag_ids.tolist())}
        self.walks = walks
        self.T, self.S = len(tag_ids), len(walks)
        self.size = 6 * self.T + 4 * (self.S - 1)
        self.tag_row = np.array(
            [index[int(t)] for w in walks for t in w.tag_ids.tolist()], dtype=np.int64
        )
        self.walk_row = np.concatenate(
            [np.full(len(w.tag_ids), s, dtype=np.int64) for s, w in enumerate(walks)]
        )
        self.tag_T_world_lin = se3_inverse(np.concatenate([w.world_T_tag for w in walks]))
        ends = np.cumsum([len(w.tag_ids) for w in walks])
        self.pairs = [np.arange(e - len(w.tag_ids), e) for w, e in zip(walks, ends, strict=True)]
        # walks with as many tags go together (their blocks stack); the first walk's placement
        # columns go to a spare row and column of the normal equations, dropped at the end
        self.groups: list[_Group] = []
        sizes = np.array([len(w.tag_ids) for w in walks])
        for n in np.unique(sizes).tolist():
            members = np.flatnonzero(sizes == n)
            pairs = np.stack([self.pairs[s] for s in members])
            tag_columns = (6 * self.tag_row[pairs][:, :, None] + np.arange(6)).reshape(
                len(members), -1
            )
            place_columns = np.where(
                members[:, None] > 0,
                6 * self.T + 4 * (members[:, None] - 1) + np.arange(4),
                self.size,
            )
            self.groups.append(
                _Group(
                    pairs=pairs,
                    information=np.stack([walks[int(s)].information for s in members]),
                    gradient=np.stack([walks[int(s)].gradient for s in members]),
                    columns=np.concatenate([tag_columns, place_columns], axis=1),
                )
            )

    def offsets(
        self, placements: FloatArray, tags: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """(P, 6) each pair's offset from its linearization point and its Jacobians: (P, 6, 6)
        by the tag's tangent (right perturbation), (P, 6, 4) by its walk's placement's."""
        world_T_tag = se3_inverse(placements)[self.walk_row] @ tags[self.tag_row]
        delta = se3_log(self.tag_T_world_lin @ world_T_tag)
        d_tag = se3_log_derivative(delta)
        adjoint = se3_adjoint(se3_inverse(world_T_tag))[:, :, PLACEMENT_AXES]
        return delta, d_tag, -d_tag @ adjoint

    def normal_equations(
        self, placements: FloatArray, tags: FloatArray
    ) -> tuple[float, FloatArray, FloatArray]:
        """The building's cost (gtsam's error: ½ of the χ² above each walk's linearization
        point), its Gauss–Newton Hessian and its gradient."""
        delta, d_tag, d_place = self.offsets(placements, tags)
        spare = self.size + 1
        hessian_index, hessian_values, gradient_index, gradient_values = [], [], [], []
        cost = 0.0
        for group in self.groups:
            G, n = group.pairs.shape
            flat = delta[group.pairs].reshape(G, 6 * n)
            information_flat = np.einsum("gij,gj->gi", group.information, flat)
            cost += float(
                np.sum(0.5 * np.einsum("gi,gi->g", flat, information_flat))
                - np.sum(group.gradient * flat)
            )
            # J = [blockdiag(D_i) | Pl]: JᵀHJ by blocks, D_iᵀ H_ij D_j, D_iᵀ (H Pl)_i, Plᵀ H Pl
            d = d_tag[group.pairs]  # (G, n, 6, 6)
            place = d_place[group.pairs].reshape(G, 6 * n, 4)
            H = group.information.reshape(G, n, 6, n, 6)
            tag_tag = np.einsum("gnab,gnamc,gmcd->gnbmd", d, H, d, optimize=True)
            H_place = (group.information @ place).reshape(G, n, 6, 4)
            tag_place = np.einsum("gnab,gnac->gnbc", d, H_place).reshape(G, 6 * n, 4)
            place_place = np.swapaxes(place, 1, 2) @ H_place.reshape(G, 6 * n, 4)
            block = np.zeros((G, 6 * n + 4, 6 * n + 4))
            block[:, : 6 * n, : 6 * n] = tag_tag.reshape(G, 6 * n, 6 * n)
            block[:, : 6 * n, 6 * n :] = tag_place
            block[:, 6 * n :, : 6 * n] = np.swapaxes(tag_place, 1, 2)
            block[:, 6 * n :, 6 * n :] = place_place
            residual = (information_flat - group.gradient).reshape(G, n, 6)
            jacobian_t_residual = np.concatenate(
                [
                    np.einsum("gnab,gna->gnb", d, residual).reshape(G, 6 * n),
                    np.einsum("gia,gi->ga", place, residual.reshape(G, 6 * n)),
                ],
                axis=1,
            )
            columns = group.columns
            hessian_index.append((columns[:, :, None] * spare + columns[:, None, :]).reshape(-1))
            hessian_values.append(block.reshape(-1))
            gradient_index.append(columns.reshape(-1))
            gradient_values.append(jacobian_t_residual.reshape(-1))
        hessian = np.bincount(
            np.concatenate(hessian_index), np.concatenate(hessian_values), minlength=spare**2
        ).reshape(spare, spare)[: self.size, : self.size]
        gradient = np.bincount(
            np.concatenate(gradient_index), np.concatenate(gradient_values), minlength=spare
        )[: self.size]
        return (
            cost,
            np.ascontiguousarray(hessian, dtype=np.float64),
            np.asarray(gradient, dtype=np.float64),
        )

    def retracted(
        self, tags: FloatArray, placements: FloatArray, step: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        T, S = self.T, self.S
        new_tags = tags @ se3_exp(step[: 6 * T].reshape(T, 6))
        tangent = np.zeros((S, 6))
        tangent[1:, list(PLACEMENT_AXES)] = step[6 * T :].reshape(S - 1, 4)
        return new_tags, placements @ se3_exp(tangent)

    def largest_step(self, step: FloatArray) -> tuple[float, float]:
        tag_steps = step[: 6 * self.T].reshape(self.T, 6)
        place_steps = step[6 * self.T :].reshape(self.S - 1, 4)
        step_m = max(
            float(np.max(np.linalg.norm(tag_steps[:, 3:], axis=1), initial=0.0)),
            float(np.max(np.linalg.norm(place_steps[:, 1:], axis=1), initial=0.0)),
        )
        step_rad = max(
            float(np.max(np.linalg.norm(tag_steps[:, :3], axis=1), initial=0.0)),
            float(np.max(np.abs(place_steps[:, 0]), initial=0.0)),
        )
        return step_m, step_rad


def _solve(matrix: FloatArray, rhs: FloatArray) -> FloatArray:
    try:
        factor = np.linalg.cholesky(matrix)
    except np.linalg.LinAlgError:
        return np.asarray(np.linalg.lstsq(matrix, rhs, rcond=None)[0], dtype=np.float64)
    return np.asarray(np.linalg.solve(factor.T, np.linalg.solve(factor, rhs)), dtype=np.float64)


# --------------------------------------------------------------------------- SE(3), as gtsam


def se3_exp(xi: FloatArray) -> FloatArray:
    """(…, 4, 4) ``Pose3.Expmap`` of (…, 6) tangents ``[rot rad, trans m]``."""
    omega, rho = xi[..., :3], xi[..., 3:]
    theta = np.linalg.norm(omega, axis=-1)[..., None, None]
    W = skew(omega)
    small = theta < 1e-6
    safe = np.where(small, 1.0, theta)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    c = np.where(small, 1.0 / 6.0 - theta**2 / 120.0, (safe - np.sin(safe)) / safe**3)
    V = np.eye(3) + b * W + c * (W @ W)
    out = np.zeros((*xi.shape[:-1], 4, 4))
    out[..., :3, :3] = so3_exp(omega)
    out[..., :3, 3] = np.einsum("...ij,...j->...i", V, rho)
    out[..., 3, 3] = 1.0
    return out


def se3_log(T: FloatArray) -> FloatArray:
    """(…, 6) ``Pose3.Logmap`` of (…, 4, 4) poses (rotations below π)."""
    omega = so3_log(T[..., :3, :3])
    theta = np.linalg.norm(omega, axis=-1)[..., None, None]
    W = skew(omega)
    small = theta < 1e-4
    safe = np.where(small, 1.0, theta)
    d = np.where(
        small,
        1.0 / 12.0 + theta**2 / 720.0,
        (1.0 - safe * np.sin(safe) / (2.0 * (1.0 - np.cos(safe)))) / safe**2,
    )
    V_inv = np.eye(3) - 0.5 * W + d * (W @ W)
    rho = np.einsum("...ij,...j->...i", V_inv, T[..., :3, 3])
    return np.concatenate([omega, rho], axis=-1)


def se3_adjoint(T: FloatArray) -> FloatArray:
    """(…, 6, 6) ``Pose3.AdjointMap``: ``[[R, 0], [[t]× R, R]]``."""
    R = T[..., :3, :3]
    out = np.zeros((*T.shape[:-2], 6, 6))
    out[..., :3, :3] = R
    out[..., 3:, 3:] = R
    out[..., 3:, :3] = skew(T[..., :3, 3]) @ R
    return out


def se3_log_derivative(xi: FloatArray) -> FloatArray:
    """(…, 6, 6) ``Pose3.LogmapDerivative`` at ``Exp(xi)`` to second order in ``xi``:
    ``I + ad_ξ / 2 + ad_ξ² / 12`` (the offsets it is used at are centimetres and milliradians)."""
    ad = np.zeros((*xi.shape[:-1], 6, 6))
    W = skew(xi[..., :3])
    ad[..., :3, :3] = W
    ad[..., 3:, 3:] = W
    ad[..., 3:, :3] = skew(xi[..., 3:])
    return np.asarray(np.eye(6) + 0.5 * ad + (ad @ ad) / 12.0, dtype=np.float64)


def offset_size(delta: FloatArray) -> tuple[float, float]:
    """The largest translation (m) and rotation (rad) among (n, 6) tangent offsets."""
    if delta.shape[0] == 0:
        return 0.0, 0.0
    return (
        float(np.max(np.linalg.norm(delta[:, 3:], axis=1))),
        float(np.max(np.linalg.norm(delta[:, :3], axis=1))),
    )


__all__ = [
    "BuildingSolution",
    "offset_size",
    "se3_adjoint",
    "se3_exp",
    "se3_log",
    "se3_log_derivative",
    "solve_building",
]
