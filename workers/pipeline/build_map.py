"""The build_map stages after ``load``: tune → optimize → evaluate → path_graph → store (a build
overtaken by a change of the map ends in :func:`_supersede`), and the stages of each job kind
(:data:`PIPELINES`)."""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import time
from collections import Counter
from collections.abc import Mapping, Sequence
from typing import Any

from sqlalchemy.orm import Session as DbSession

from app.domain.evaluation.metrics import joint_shift_metric, shift_metric
from app.domain.evaluation.sweep_plan import SweepPlan
from app.domain.evaluation.table import compare_walk, evaluate_map
from app.domain.evaluation.tuning import SearchSpace, Trial, TuningTarget, best_trial
from app.domain.formats.derived_documents import APP_MAP_EXPORT, packed_documents
from app.domain.formats.map_io import map_from_json, map_to_app_format, map_to_json
from app.domain.json_values import finite_or_none
from app.domain.mapping.noise import COMPONENTS
from app.domain.mapping.slam import optimize_session
from app.domain.navigation.path_graph import (
    ELEVATOR,
    JUNCTION,
    STAIRS,
    path_graph_from_json,
    path_graph_to_json,
)
from app.domain.navigation.skeleton import build_skeleton
from app.render.map_plot import render_map_png
from app.storage import blobs, maps, queue
from app.storage.sessions import (
    AUTO_TUNE_TRIALS,
    BUILD_MAP,
    SESSION_IDS,
)
from workers import incremental_builds
from workers.failures import log_failure

from .context import JobContext, PermanentJobError, Stage, need
from .joint import optimize_joint
from .loading import load

#: the package's one logger (its records keep the name they had before the split)
logger = logging.getLogger("workers.pipeline")


def tune(ctx: JobContext) -> None:
    """With ``auto_tune_trials`` N > 0: choose the noise variances by the shift metric (Optuna's
    sampler, N trials over the paper grid's box, warm-started) before the final optimization."""
    if ctx.auto_tune_trials <= 0:
        return
    session, params = need(ctx.session, "session"), need(ctx.params, "params")
    target = TuningTarget.prepare(session, params)
    plan = SweepPlan(method="sampler", space=SearchSpace.paper_grid(), trials=ctx.auto_tune_trials)
    trials: list[Trial] = []
    while batch := plan.next_batch(trials, len(trials)):
        for values in batch:
            ctx.check_interrupted()
            trials.append(target.run(values, on_iteration=ctx.on_trial_iteration))
            ctx.report(len(trials) / plan.total)
    best = best_trial(trials, "shift")
    if best is None:
        ctx.log(f"tune: no trial of {len(trials)} converged; keeping the parameters")
        return
    ctx.params = params.with_overrides(best.values)
    shift_pre = target.baseline()[0]
    ctx.log(
        f"tune: {len(trials)} trials, shift {shift_pre:.4g} (pre-optimized) → {best.shift:.4g} "
        f"with {', '.join(f'{k}={v:.3g}' for k, v in best.values.items())}"
    )


def optimize(ctx: JobContext) -> None:
    """Graph SLAM; progress per Levenberg–Marquardt iteration (an estimate: LM stops early)."""
    if ctx.sessions:
        optimize_joint(ctx)
        return
    session = need(ctx.session, "session")

    def on_iteration(iteration: int, _error: float) -> None:
        ctx.report(1.0 - 0.6**iteration)
        ctx.check_interrupted()  # a cancel stops the optimization here, not after it

    started_s = time.perf_counter()
    ctx.result = optimize_session(session, need(ctx.params, "params"), on_iteration=on_iteration)
    stats = ctx.result.stats
    if len(session.detections) > 0 and ctx.result.detections_used == 0:
        counts = ", ".join(f"{n} {why}" for why, n in sorted(ctx.result.rejection_counts().items()))
        raise PermanentJobError(
            f"every one of the session's {len(session.detections)} tag detections was rejected "
            f"({counts}): the map would have no tags; loosen the screening parameters"
        )
    noise = ctx.result.noise
    estimated = ""
    if noise is not None:  # one line per stage: the walk's noise goes on the optimize line
        variances = noise.variances(need(ctx.params, "params"))
        estimated = (
            f"; noise from the walk's residuals ({noise.rounds} rounds): odometry "
            f"{variances.odom_linear_var_m2_per_s:.3g} m²/s and "
            f"{variances.odom_angular_var_rad2_per_s:.3g} rad²/s, tags "
            f"{variances.tag_position_var_m2:.3g} m² at 1 m and "
            f"{variances.tag_orientation_var_rad2:.3g} rad²"
            + (f" ({noise.note})" if noise.note else "")
        )
    ctx.log(
        f"optimize: {stats.iterations} iterations, error {stats.initial_error:.6g} → "
        f"{stats.final_error:.6g}, {len(ctx.result.rejections)} detections rejected, "
        f"{(time.perf_counter() - started_s) * 1e3:.0f} ms{estimated}"
    )


def _session_contributions(ctx: JobContext) -> list[dict[str, Any]] | None:
    """What each session of a joint map contributed (a version's ``statistics["sessions"]``):
    its share of the map, what it weighs and why (its noise estimated alone, the factor joining
    raised its variances by, its odometry scale), and how its own map alone compares with the
    building map on all its tags, its shared ones and its own ones (how far joining moved them
    after a rigid fit, and the shift metric over its own sightings: no ground truth here)."""
    joint = ctx.joint
    if joint is None:
        return None
    params = need(ctx.params, "params")
    out = []
    for session_id, part, session, mask in zip(
        ctx.session_ids, joint.parts, joint.sessions, joint.session_masks(), strict=True
    ):
        report = compare_walk(joint, part, part.alone) if part.alone is not None else None
        out.append(
            {
                "session_id": session_id,
                "poses": part.pose_rows.stop - part.pose_rows.start,
                "first_pose_row": part.pose_rows.start,
                "tags": list(part.tag_ids),
                "detections_used": part.detections_used,
                "detections_rejected": part.detections_rejected,
                "tag_chi2_mean": None if math.isnan(part.tag_chi2_mean) else part.tag_chi2_mean,
                "shared_tags": list(part.alignment.shared_tags),
                "placed_by_tags": list(part.alignment.inlier_tags),
                "own_landmark_tags": list(part.local_tags),
                "odometry_variance_scale": part.odometry_variance_scale,
                "tag_depth_scale": part.tag_depth_scale,
                "yaw_rad": part.alignment.yaw_rad,
                "odometry_scale": part.alignment.odometry_scale,
                "noise": None if part.noise is None else part.noise.to_dict(params),
                "noise_scales": dict(zip(COMPONENTS, part.noise_scales.tolist(), strict=True)),
                "disagreement_factor": part.disagreement_factor,
                "cost_alone": finite_or_none(part.cost_alone),
                "cost_joint": finite_or_none(part.cost_joint),
                "redundancy_gain": part.redundancy_gain,
                "weighting": part.weighting,
                "alone_vs_joint": None
                if report is None or part.alone is None
                else {
                    "all": report.all_tags.to_dict(),
                    "shared": report.shared.to_dict(),
                    "own": report.own.to_dict(),
                    "shift_alone": finite_or_none(
                        shift_metric(session, part.alone.tag_poses(), detection_mask=mask)
                    ),
                    "shift_joint": finite_or_none(
                        shift_metric(session, joint.map.tag_poses(), detection_mask=mask)
                    ),
                },
            }
        )
    return out


def evaluate(ctx: JobContext) -> None:
    """Shift metric, the ground-truth metric when the job has ground truth, and the top-down
    plot."""
    session = need(ctx.session, "session")
    result = need(ctx.result, "result")
    ctx.evaluation = evaluate_map(session, result, ctx.ground_truth)
    if ctx.joint is not None:  # the shift metric over each session's own detections
        ctx.evaluation = dataclasses.replace(
            ctx.evaluation,
            shift_pre=joint_shift_metric(ctx.joint, result.tag_poses_pre()),
            shift_opt=joint_shift_metric(ctx.joint),
        )
    ctx.report(0.5)
    try:
        ctx.plot_png = render_map_png(result, session)
    except Exception as err:  # a plot is a picture of the map: the map is built without one
        logger.warning("job %d: the plot failed", ctx.lease.job_id, exc_info=True)
        ctx.log(f"evaluate: no plot ({type(err).__name__}); the map is stored without one")
        ctx.plot_png = None
    evaluation = ctx.evaluation
    truth = (
        f"ground-truth metric {evaluation.gt_metric_opt:.4g} "
        f"(pre-optimized {evaluation.gt_metric_pre:.4g}, "
        f"{evaluation.tags_with_ground_truth} tags), "
        if ctx.ground_truth is not None
        else ""
    )
    ctx.log(
        f"evaluate: shift metric {evaluation.shift_opt:.4g} "
        f"(pre-optimized {evaluation.shift_pre:.4g}), {truth}"
        + (f"plot {len(ctx.plot_png) / 1e3:.0f} kB" if ctx.plot_png is not None else "no plot")
    )


def path_graph(ctx: JobContext) -> None:
    """Where a pedestrian can walk: the corridor skeleton of the optimized path (passes merged
    into centrelines, junctions where corridors branch), floors, stairs and elevators, and the
    tags and points of interest attached to it (app.domain.navigation.skeleton). A map of several
    sessions gets one skeleton fused from all its walks (issue 26).
    """
    result = need(ctx.result, "result")
    walk_starts = [0] if ctx.joint is None else [p.pose_rows.start for p in ctx.joint.parts]
    graph = build_skeleton(result, walk_starts=walk_starts)
    ctx.path_graph = path_graph_to_json(graph)
    # what the app-map had to adjust (a walk that falls apart, repeated names) is the map's news
    notes = map_to_app_format(result, path_graph=graph)["notes"]
    if notes:
        ctx.result = dataclasses.replace(
            result, warnings=(*result.warnings, *(f"app map: {note}" for note in notes))
        )
        for note in notes:
            ctx.log(f"app map: {note}")
    walk = graph.graph
    kinds = Counter(walk.edges[u, v]["kind"] for u, v in walk.edges)
    junctions = sum(1 for node in walk.nodes if walk.nodes[node]["kind"] == JUNCTION)
    ctx.log(
        f"path graph: corridor skeleton{_fused_from(len(walk_starts))}, "
        f"{walk.number_of_nodes()} nodes ({junctions} junctions), "
        f"{walk.number_of_edges()} edges ({kinds[STAIRS]} stairs, {kinds[ELEVATOR]} "
        f"elevator), {len(graph.floor_levels_m)} floor(s)"
    )


def _fused_from(walks: int) -> str:
    return f" fused from {walks} walks" if walks > 1 else " of 1 walk"


def derived_documents(ctx: JobContext, document: dict[str, Any]) -> maps.DerivedDocuments:
    """What the API would otherwise make of the stored version on every process's first request
    (issue 19, finding 3), made once here from the version as stored (its map document read
    back, the path graph through JSON) so that it equals what the API makes: the app's map file
    (``app.domain.formats.derived_documents.app_map_bytes``) and the dashboard's overview.
    ``document``: the version's map document (``map_to_json`` of the result)."""
    stored = map_from_json(document)  # JSON keeps its floats exactly: no round trip needed
    graph = (
        None
        if ctx.path_graph is None
        else path_graph_from_json(json.loads(json.dumps(ctx.path_graph, allow_nan=False)))
    )
    app_map_gzip, overview_gzip = packed_documents(
        stored,
        ctx.session if ctx.joint is None else None,
        graph,
        sessions=_session_contributions(ctx) or [],
    )
    return maps.DerivedDocuments(
        app_map_gzip=app_map_gzip, app_map_export=APP_MAP_EXPORT, overview_gzip=overview_gzip
    )


def store(ctx: JobContext) -> None:
    """Write the version's bulk data (map document, plot, path graph) and what is derived from
    it (:func:`derived_documents`) as blobs, each chunk in a small transaction of its own;
    then, in ONE small transaction: end the job as succeeded (fenced: raises LeaseLost, and the
    transaction rolls back, if the lease is gone) and add the map version that refers to the
    blobs. So the build's write lock (SQLite's only one) is held
    for milliseconds, not for the seconds the bulk data takes (issue 19, finding 4). Afterwards,
    blobs nobody refers to for an hour (a failed attempt's, a deleted map's) are collected.

    The version is stored only if the map is still at the generation the build was queued for
    (``maps.generation_for_store``, under the map's lock, first thing in that transaction); a
    build overtaken by a change of the map is superseded instead (:func:`_supersede`), and if
    that is already known before the bulk data is written, none is written."""
    session = need(ctx.session, "session")
    result = need(ctx.result, "result")
    map_id = need(ctx.lease.map_id, "map_id")
    with ctx.db.read() as tx:  # overtaken already: write no bulk data for nothing
        seen = maps.map_generation(tx, map_id)
    if seen is not None and seen != ctx.map_generation:
        with ctx.db.transaction() as tx:
            generation = maps.generation_for_store(tx, map_id)
            if generation is not None and generation != ctx.map_generation:
                _supersede(ctx, tx, map_id, generation)
                return
    document = map_to_json(result)
    derived: maps.DerivedDocuments | None
    try:
        derived = derived_documents(ctx, document)
    except Exception as err:  # what the API would make: it makes it then, as for older versions
        logger.warning("job %d: the derived documents failed", ctx.lease.job_id, exc_info=True)
        derived, made = None, f"no app-map or overview stored ({type(err).__name__})"
    else:
        made = (
            f"app-map {len(derived.app_map_gzip) / 1e3:.0f} kB, "
            f"overview {len(derived.overview_gzip) / 1e3:.0f} kB (gzip)"
        )
    ctx.log(f"store: map {map_id}, {len(result.tag_ids)} tags, {session.num_poses} poses; {made}")
    bulk = maps.write_version_bulk(
        ctx.db,
        result=result,
        document=document,
        plot_png=ctx.plot_png,
        path_graph=ctx.path_graph,
        derived=derived,
    )
    ctx.report(0.9)
    with ctx.db.transaction() as tx:
        # the map first, then the job: the order every change of the map takes
        now = maps.generation_for_store(tx, map_id)
        if now is not None and now != ctx.map_generation:
            _supersede(ctx, tx, map_id, now)
            return
        queue.finish(tx, ctx.lease, log_tail=ctx.log_tail)
        ctx.version = maps.store_version(
            tx,
            map_id=map_id,
            job_id=ctx.lease.job_id,
            result=result,
            evaluation=need(ctx.evaluation, "evaluation"),
            path_length_m=(
                sum(s.path_length_m() for s in ctx.sessions)
                if ctx.sessions
                else session.path_length_m()
            ),
            session_ids=ctx.session_ids,
            sessions=_session_contributions(ctx),
            bulk=bulk,
            generation=ctx.map_generation,
        )
        if ctx.isam_state is not None:  # in the version's transaction: never one without it
            incremental_builds.save_state(
                tx, map_id, ctx.version.id, ctx.isam_state, ctx.lease.job_id
            )
    ctx.finished = True
    try:
        collected = blobs.collect_orphan_blobs(ctx.db)
    except Exception as err:  # the map is stored; the orphans wait for the next build
        log_failure(logger, f"job {ctx.lease.job_id}: collecting orphan blobs failed", err)
    else:
        if collected:
            logger.info("job %d: %d orphan blobs collected", ctx.lease.job_id, collected)


def _supersede(ctx: JobContext, tx: DbSession, map_id: int, generation: int) -> None:
    """End the build without storing its version: map ``map_id`` changed while it was built
    (its generation is ``generation`` now, the build's ``ctx.map_generation``), so its result is
    not of the map's current sessions and parameters. (Dropped, not kept as a version: the
    newest version is the current one everywhere — the API, the app-map, localization — and a
    version of an old set can be made again by a rebuild with its ``session_ids``.) The build of
    the current generation is the change's own job; only if there is none at all (nothing else
    makes one) is one queued here, from the map's sessions with this build's parameters."""
    jobs = [
        job
        for job in queue.jobs_of_map(tx, map_id, kind=BUILD_MAP)
        if (job.map_generation or 0) == generation
    ]
    if jobs:
        follow_up = jobs[-1]
        builds = f"job {follow_up.id} ({follow_up.state}) builds"
    else:
        overrides = {
            name: value
            for name, value in ctx.lease.params.items()
            if name not in (SESSION_IDS, AUTO_TUNE_TRIALS)
        }
        ids = maps.map_session_ids(tx, map_id)
        params = dict(overrides)
        if len(ids) > 1:
            params[SESSION_IDS] = ids
        job_id = queue.enqueue(
            tx,
            kind=BUILD_MAP,
            map_id=map_id,
            session_id=ids[0],
            params=params,
            max_attempts=ctx.lease.max_attempts,
            map_generation=generation,
        )
        builds = f"job {job_id} (queued now) builds"
    reason = (
        f"map {map_id} changed while it was built (generation {ctx.map_generation} → "
        f"{generation}); its version is not stored: {builds} the map's current sessions"
    )
    queue.supersede(tx, ctx.lease, reason=reason, log_tail=ctx.log_tail)
    ctx.finished = ctx.superseded = True


BUILD_MAP_STAGES: tuple[Stage, ...] = (
    Stage(name="load", weight=0.2, run=load),
    Stage(name="tune", weight=0.3, run=tune),
    Stage(name="optimize", weight=0.3, run=optimize),
    Stage(name="evaluate", weight=0.12, run=evaluate),
    Stage(name="path_graph", weight=0.03, run=path_graph),
    Stage(name="store", weight=0.05, run=store),
)

#: The stages of each job kind a worker runs.
PIPELINES: Mapping[str, Sequence[Stage]] = {BUILD_MAP: BUILD_MAP_STAGES}
