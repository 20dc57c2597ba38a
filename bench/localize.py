"""Live-localization benchmark: one command, prints a table.

    .venv/bin/python bench/localize.py              # simulation, real cross-session, update cost
    .venv/bin/python bench/localize.py --quick      # 100 and 1,000 poses only for the cost
    .venv/bin/python bench/localize.py --json out.json

Accuracy (``app.domain.localize.update`` in batches of ``--batch`` poses, as a phone would send):

- simulation, phone position error: a building from ``app.domain.evaluation.simulate``; the map is
  either the true tags (the localizer alone) or the map optimized from a first walk
  (``optimize_session``, default ``SlamParams``); then a *second* walk through the same building,
  with its own route and noise, is replayed in its own session frame (turned and moved off the map
  frame). At every update once localized, the distance between ``map_T_phone`` and the true phone
  position, m. An optimized map sits where its own gauge (its first pose) put it, so the truth is
  first carried onto it by the best-fit rigid transform of the tags (``umeyama_rigid``, as the tag
  RMSE does).
- real, cross-session next-tag prediction: the map optimized from ``floor_2_straight``; the replay
  of ``desnat_straight_once`` (same floor, tags 300–307). At each tag detection, before the update
  that carries it, the distance between the map's tag and where the current estimate puts the
  detected tag, m: over all detections, and over the first detection of each new tag sighting
  (the "next tag" of a navigating user; later detections repeat a tag just used).

Cost: wall time of ``update`` (and of ``update`` with the state's JSON round trip, as the API does
between requests) over a whole simulated walk of 100, 1,000 and 10,000 poses (p50 and p99 over all
updates, and apart for the updates that carried tag detections, which run the smoother, and those
that did not, which only follow the odometry), with the largest window reached and the stored
state's size.

The second walk needs the simulator's building without its walk, so this file builds it
(``build_building``) from the building's seed and records a walk through it (``record_walk``) from
a walk seed; ``simulate_session`` ties both to one seed.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # run from a checkout without installing

from app.cli.tables import render_markdown_table  # noqa: E402
from app.domain.evaluation import simulate as sim_module  # noqa: E402
from app.domain.evaluation.metrics import tag_rmse_m, umeyama_rigid  # noqa: E402
from app.domain.evaluation.simulate import SimulationConfig, simulate_session  # noqa: E402
from app.domain.frames import (  # noqa: E402
    FloatArray,
    make_pose,
    rotation_about_y,
    se3_inverse,
)
from app.domain.localize import (  # noqa: E402
    LocalizerParams,
    LocalizerState,
    median_and_p90,
    parse_update,
    prediction_errors_m,
    replay_session,
    session_update_documents,
    update,
)
from app.domain.mapping.slam import optimize_session  # noqa: E402
from app.domain.upload.session import Session, load_session, parse_session  # noqa: E402

SESSIONS = REPO / "data" / "sessions"
COST_POSES = (100, 1_000, 10_000)
#: The navigation session's frame seen from the map: turned 2 rad about gravity, moved 25 m.
MAP_T_SESSION_TRUE = make_pose(rotation_about_y(2.0), [12.0, -0.4, -21.0])
TARGETS = (
    "targets: simulation median position error ≤ 0.2 m; real next-tag prediction median ≤ 0.3 m; "
    "update cost flat from 100 to 10,000 poses"
)


# --------------------------------------------------------------------------- simulation


def second_walk(config: SimulationConfig, *, walk_seed: int) -> sim_module.SimulatedSession:
    """A walk through ``config``'s building (its ``seed``) with route and noise from ``walk_seed``.

    ``simulate_session`` with the same steps (``record_walk``), but the building from
    ``config.seed``'s stream and everything else from ``walk_seed``'s.
    """
    building_stream = np.random.SeedSequence(config.seed).spawn(6)[0]
    streams = np.random.SeedSequence(walk_seed).spawn(6)
    rng_walk, rng_odometry, rng_tags, rng_outliers, rng_poi = (
        np.random.default_rng(s) for s in streams[1:]
    )
    building = sim_module.build_building(config, np.random.default_rng(building_stream))
    return sim_module.record_walk(
        config, building, (rng_walk, rng_odometry, rng_tags, rng_outliers, rng_poi)
    )


def in_session_frame(session: Session, map_T_session: FloatArray) -> Session:
    """``session`` with its odometry expressed in a frame placed at ``map_T_session``."""
    return dataclasses.replace(
        session, world_T_phone=se3_inverse(map_T_session) @ session.world_T_phone
    )


def simulated_errors(
    *, num_poses: int, map_kind: str, seed: int, batch_size: int, params: LocalizerParams
) -> dict[str, Any]:
    """Phone position errors (m) of a second walk localized against a map of the building."""
    config = SimulationConfig(num_poses=num_poses, seed=seed)
    mapping = simulate_session(config)
    if map_kind == "truth":
        map_tags = dict(mapping.world_T_tag_true)
    else:
        map_tags = optimize_session(parse_session(mapping.upload)).tag_poses()
    # The truth in the map's frame: an optimized map is placed by its own gauge (its first pose),
    # so the truth is carried onto it by the best-fit rigid transform of the tags (architecture §4).
    common = sorted(map_tags)
    map_T_truth = umeyama_rigid(
        np.stack([mapping.world_T_tag_true[t][:3, 3] for t in common]),
        np.stack([map_tags[t][:3, 3] for t in common]),
    )
    walk = second_walk(config, walk_seed=1000 + seed)
    session = in_session_frame(parse_session(walk.upload), map_T_truth @ MAP_T_SESSION_TRUE)
    steps = replay_session(map_tags, session, batch_size, params)
    errors = []
    first_localized: int | None = None
    for step in steps:
        result = step.result
        if result.map_T_phone is None or result.pose_id is None:
            continue
        if first_localized is None:
            first_localized = result.pose_id
        truth = map_T_truth @ walk.world_T_phone_true[result.pose_id]
        errors.append(float(np.linalg.norm(result.map_T_phone[:3, 3] - truth[:3, 3])))
    return {
        "errors_m": errors,
        "map_rmse_m": tag_rmse_m(map_tags, mapping.world_T_tag_true),
        "first_localized_pose": first_localized,
        "sigma_m": [s.result.position_sigma_m for s in steps if s.result.position_sigma_m],
        "predictions_m": prediction_errors_m(steps, first_of_sighting_only=True).tolist(),
    }


# --------------------------------------------------------------------------- real data


def real_cross_session(batch_size: int, params: LocalizerParams) -> dict[str, Any]:
    """Next-tag prediction errors (m) of ``desnat_straight_once`` against ``floor_2_straight``."""
    map_tags = optimize_session(load_session(SESSIONS / "floor_2_straight.json")).tag_poses()
    session = load_session(SESSIONS / "desnat_straight_once.json")
    steps = replay_session(map_tags, session, batch_size, params)
    return {
        "all_m": prediction_errors_m(steps).tolist(),
        "first_m": prediction_errors_m(steps, first_of_sighting_only=True).tolist(),
        "sigma_m": [s.result.position_sigma_m for s in steps if s.result.position_sigma_m],
    }


# --------------------------------------------------------------------------- cost


def update_cost(num_poses: int, batch_size: int, params: LocalizerParams) -> dict[str, Any]:
    """Wall time per update (ms) over a simulated walk, and with the state's JSON round trip."""
    config = SimulationConfig(
        num_poses=num_poses, seed=5, blocks=(3, 2) if num_poses > 2000 else (2, 1)
    )
    sim = simulate_session(config)
    session = parse_session(sim.upload)
    map_tags = dict(sim.world_T_tag_true)
    batches = [parse_update(d) for d in session_update_documents(session, batch_size)]
    state = LocalizerState.initial()
    update_ms, round_trip_ms, with_tags = [], [], []
    max_window = 0
    for batch in batches:
        started = time.perf_counter()
        state, result = update(state, batch, map_tags, params)
        update_ms.append((time.perf_counter() - started) * 1e3)
        started = time.perf_counter()
        state = LocalizerState.from_json(json.loads(json.dumps(state.to_json())))
        round_trip_ms.append(update_ms[-1] + (time.perf_counter() - started) * 1e3)
        with_tags.append(result.detections_used > 0)
        max_window = max(max_window, result.window_keyframes)
    ms = np.array(update_ms)
    tagged = np.array(with_tags)

    def percentile(values: FloatArray, q: float) -> float:
        return float(np.percentile(values, q)) if values.size else math.nan

    return {
        "poses": num_poses,
        "updates": len(batches),
        "tagged_updates": int(tagged.sum()),
        "p50_ms": percentile(ms, 50),
        "p99_ms": percentile(ms, 99),
        "tagged_p50_ms": percentile(ms[tagged], 50),
        "tagged_p99_ms": percentile(ms[tagged], 99),
        "untagged_p50_ms": percentile(ms[~tagged], 50),
        "json_p50_ms": percentile(np.array(round_trip_ms), 50),
        "json_p99_ms": percentile(np.array(round_trip_ms), 99),
        "max_window": max_window,
        "state_kb": len(json.dumps(state.to_json())) / 1024,
    }


# --------------------------------------------------------------------------- main


def fmt(value: float, pattern: str = "{:.3f}") -> str:
    return (
        "–"
        if value is None or (isinstance(value, float) and math.isnan(value))
        else pattern.format(value)
    )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="cost at 100 and 1,000 poses only")
    parser.add_argument("--batch", type=int, default=10, help="poses per update")
    parser.add_argument("--seeds", type=int, default=5, help="simulated buildings")
    parser.add_argument("--sim-poses", type=int, default=3_000, help="poses per simulated walk")
    parser.add_argument("--json", type=Path, help="also write the numbers here")
    args = parser.parse_args()
    params = LocalizerParams()
    out: dict[str, Any] = {}

    accuracy = [["case", "what", "n", "median m", "p90 m", "median σ m"]]
    for map_kind in ("truth", "optimized"):
        errors: list[float] = []
        sigmas: list[float] = []
        for seed in range(args.seeds):
            print(f"simulation, {map_kind} map, building {seed} …", file=sys.stderr, flush=True)
            row = simulated_errors(
                num_poses=args.sim_poses,
                map_kind=map_kind,
                seed=seed,
                batch_size=args.batch,
                params=params,
            )
            errors += row["errors_m"]
            sigmas += row["sigma_m"]
        median, p90 = median_and_p90(errors)
        out[f"simulation_{map_kind}"] = {"median_m": median, "p90_m": p90, "n": len(errors)}
        accuracy.append(
            [
                f"simulation, {map_kind} map ({args.seeds} buildings × {args.sim_poses} poses)",
                "phone position error",
                str(len(errors)),
                fmt(median),
                fmt(p90),
                fmt(statistics.median(sigmas) if sigmas else math.nan),
            ]
        )

    print("real cross-session replay …", file=sys.stderr, flush=True)
    real = real_cross_session(args.batch, params)
    sigma = statistics.median(real["sigma_m"]) if real["sigma_m"] else math.nan
    for key, what in (
        ("first_m", "next-tag prediction, first detection of each sighting"),
        ("all_m", "tag prediction, every detection"),
    ):
        median, p90 = median_and_p90(real[key])
        out[f"real_{key}"] = {"median_m": median, "p90_m": p90, "n": len(real[key])}
        accuracy.append(
            [
                "real: floor_2_straight map, desnat_straight_once replay",
                what,
                str(len(real[key])),
                fmt(median),
                fmt(p90),
                fmt(sigma),
            ]
        )
    print(render_markdown_table(accuracy))
    print()

    cost = [
        [
            "poses",
            "updates (with tags)",
            "p50 ms",
            "p99 ms",
            "with tags p50 ms",
            "with tags p99 ms",
            "without p50 ms",
            "+JSON p50 ms",
            "+JSON p99 ms",
            "max window",
            "state KiB",
        ]
    ]
    for num_poses in COST_POSES:
        if args.quick and num_poses > 1_000:
            continue
        print(f"update cost, {num_poses} poses …", file=sys.stderr, flush=True)
        row = update_cost(num_poses, args.batch, params)
        out[f"cost_{num_poses}"] = row
        cost.append(
            [
                str(row["poses"]),
                f"{row['updates']} ({row['tagged_updates']})",
                fmt(row["p50_ms"], "{:.2f}"),
                fmt(row["p99_ms"], "{:.2f}"),
                fmt(row["tagged_p50_ms"], "{:.2f}"),
                fmt(row["tagged_p99_ms"], "{:.2f}"),
                fmt(row["untagged_p50_ms"], "{:.2f}"),
                fmt(row["json_p50_ms"], "{:.2f}"),
                fmt(row["json_p99_ms"], "{:.2f}"),
                str(row["max_window"]),
                fmt(row["state_kb"], "{:.1f}"),
            ]
        )
    print(render_markdown_table(cost, justify="right"))
    print(TARGETS)
    if args.json:
        args.json.write_text(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
