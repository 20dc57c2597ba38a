"""One session's factor graph for many noise settings (a sweep's trials): :class:`TrialGraph`,
which rebuilds only the kinds of factor a setting changes (``*_NOISE_FIELDS``)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import gtsam
from gtsam.symbol_shorthand import L

from app.domain.frames import FloatArray
from app.domain.mapping.params import SlamParams

from .factors import (
    build_gauge_prior,
    build_gravity_factors,
    build_odometry_factors,
    build_tag_factors,
    factor_graph,
)
from .inputs import GraphInputs
from .optimizer import IterationCallback, levenberg_marquardt


def optimize_tag_poses(
    inputs: GraphInputs, params: SlamParams
) -> tuple[dict[int, FloatArray], int, gtsam.Values]:
    """The optimized ``world_T_tag`` of every tag in the graph, the number of LM iterations and
    the solution (no residuals, no marginals), one LM run from the initial values (raw odometry
    and first observations). ``params``' noise fields are used as given (no estimate); its
    rejection thresholds were applied when ``inputs`` were prepared. For many settings of one
    session, keep a :class:`TrialGraph` instead: it rebuilds only what a setting changes."""
    return TrialGraph(inputs).optimize(params)


#: The ``SlamParams`` fields each kind of factor is built from (besides ``GraphInputs``).
ODOMETRY_NOISE_FIELDS = ("odom_linear_var_m2_per_s", "odom_angular_var_rad2_per_s")
#: (the angular rate too: the gravity of the poses between keyframes is folded in through it)
GRAVITY_NOISE_FIELDS = ("gravity_var_rad2", "odom_angular_var_rad2_per_s")
TAG_NOISE_FIELDS = (
    "tag_position_var_m2",
    "tag_depth_var_ratio",
    "tag_orientation_var_rad2",
    "huber_k",
)


class TrialGraph:
    """One session's factor graph for many noise settings (a sweep's trials).

    The graph of a setting is the one :func:`optimize_session` builds, factor for factor and in
    the same order, so LM takes the same steps on it. What no setting changes is done once: the
    gauge prior, and the COLAMD ordering (the graph's structure is the same for every setting).
    Each kind of factor (odometry, gravity, tags) is rebuilt only when one of the parameters it
    is built from (``*_NOISE_FIELDS``) differs from the previous setting's; on the paper grid,
    where the odometry angular variance varies fastest, that leaves the ~N odometry factors and
    the K gravity factors.
    """

    def __init__(self, inputs: GraphInputs) -> None:
        self.inputs = inputs
        self._prior = factor_graph([build_gauge_prior(inputs)])
        self._kinds: dict[str, tuple[tuple[float, ...], gtsam.NonlinearFactorGraph]] = {}
        self._ordering: gtsam.Ordering | None = None

    def graph(self, params: SlamParams) -> gtsam.NonlinearFactorGraph:
        """The factor graph with ``params``' noise models."""
        inputs = self.inputs
        graph = gtsam.NonlinearFactorGraph()
        graph.push_back(self._prior)
        graph.push_back(
            self._kind("odometry", ODOMETRY_NOISE_FIELDS, params, build_odometry_factors, inputs)
        )
        graph.push_back(
            self._kind("gravity", GRAVITY_NOISE_FIELDS, params, build_gravity_factors, inputs)
        )
        graph.push_back(
            self._kind(
                "tags", TAG_NOISE_FIELDS, params, lambda i, p: build_tag_factors(i, p)[0], inputs
            )
        )
        return graph

    def optimize(
        self, params: SlamParams, *, on_iteration: IterationCallback | None = None
    ) -> tuple[dict[int, FloatArray], int, gtsam.Values]:
        """As :func:`optimize_tag_poses`: LM from the initial values (a build's first stage)."""
        return self.refine(params, self.inputs.initial, on_iteration=on_iteration)

    def refine(
        self,
        params: SlamParams,
        start: gtsam.Values,
        *,
        on_iteration: IterationCallback | None = None,
    ) -> tuple[dict[int, FloatArray], int, gtsam.Values]:
        """LM with ``params`` from ``start`` (the optimum with other variances, for a build's
        second stage): the tag poses, the iterations and the solution. ``on_iteration(iteration,
        error)`` is called after each LM iteration, as in :func:`optimize_session`; whatever it
        raises stops the optimization there and propagates (a job's cancel check)."""
        graph = self.graph(params)
        if self._ordering is None:
            self._ordering = gtsam.Ordering.ColamdNonlinearFactorGraph(graph)
        values, iterations, _ = levenberg_marquardt(
            graph, start, params, on_iteration, ordering=self._ordering
        )
        poses = {
            tag_id: values.atPose3(L(tag_id)).matrix() for tag_id in sorted(self.inputs.tag_rows)
        }
        return poses, iterations, values

    def _kind(
        self,
        kind: str,
        fields: tuple[str, ...],
        params: SlamParams,
        build: Callable[[GraphInputs, SlamParams], list[Any]],
        inputs: GraphInputs,
    ) -> gtsam.NonlinearFactorGraph:
        key = tuple(float(getattr(params, name)) for name in fields)
        cached = self._kinds.get(kind)
        if cached is not None and cached[0] == key:
            return cached[1]
        factors = factor_graph(build(inputs, params))
        self._kinds[kind] = (key, factors)
        return factors
