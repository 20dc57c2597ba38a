"""Building maps that grow a walk at a time (issue 38): one command, prints the tables.

    .venv/bin/python bench/incremental.py               # N = 5, 20, 50, 100, 200 (long)
    .venv/bin/python bench/incremental.py --quick       # N = 5, 20
    .venv/bin/python bench/incremental.py --sizes 50 --batch-max 50 --json out.json
    .venv/bin/python bench/incremental.py --isam-only --isam 5 20 50 100 200   # ISAM2 engine

For each N: N + 1 simulated walks of one building (``simulate_building_sessions``, seed 7, 1,200
poses = 2 minutes each, as bench/multi_session.py's table 4), then, each in CPU seconds
(``time.process_time``, OpenBLAS held to one thread: timings on the shared machine are noisy, CPU
time less so):

- *first build*: ``incremental.build`` of the first N walks;
- *add*: walk N + 1 added to that state (``add_walk``), and how many walks it relinearized;
- *remove*: the same walk removed again (``remove_walk``);
- *peak MiB*: the process's peak resident memory after these three (``ru_maxrss``; every
  session of the building is in memory, as a worker that relinearizes old walks would load
  them) and the state's size as stored (the building row and the walks' rows);
- for N + 1 ≤ ``--batch-max``: the batch build (``joint.optimize_sessions``) of the N walks
  (cold) and of the N + 1 (warm from it: what the worker does today on an add), and the largest
  tag and pose distance between what the incremental state serves and the batch map of the same
  walks (same gauge: both are drawn in the first walk's world), for the build, the add and the
  removal; and whether the batch map down-weighted a walk, rescaled one or set a tag apart
  (which the summaries do not reproduce: docs/multi-session.md).

Each N runs in a process of its own (its peak memory is its own). Then the shipped walks of the
mac building (floor_2_straight, desnat_straight_once, straight_209_occam whole, and
oblique_209_occam when it ships): the first two built, the third added, against the batch build
of all three, with and without its down-weighting.

With ``--isam N …``: the ISAM2 engine (``incremental.IsamBuilding``) on the same buildings, each N
in a process of its own: the first build, walk N + 1 added and taken out again (and the ISAM2
updates each took), the state written as rows, and the tree made again from those rows (a
restarted worker), with their distances to the batch build of the same walks (for N + 1 ≤
``--batch-max``) and the peak memory before the batch build runs (the simulation's included;
in brackets the resident memory of the parsed sessions before the build, and what the build
added to it). ``--isam-only`` skips the summary design's tables.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import dataclasses
import json
import resource
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # run from a checkout without installing

from app.cli.tables import render_markdown_table  # noqa: E402
from app.domain.evaluation.simulate import SimulationConfig  # noqa: E402
from app.domain.evaluation.simulate_building import (  # noqa: E402
    MIXED_WALKS,
    simulate_building_sessions,
)
from app.domain.mapping.incremental import (  # noqa: E402
    IncrementalMap,
    IsamBuilding,
    Walk,
    add_walk,
    build,
    remove_walk,
)
from app.domain.mapping.joint import JointMap, optimize_sessions  # noqa: E402
from app.domain.mapping.params import SlamParams  # noqa: E402
from app.domain.mapping.slam import optimize_session  # noqa: E402
from app.domain.upload.session import Session, load_session, parse_session  # noqa: E402

SESSIONS = REPO / "data" / "sessions"
MAC_WALKS = ("floor_2_straight", "desnat_straight_once", "straight_209_occam", "oblique_209_occam")
SIMULATED_POSES = 1_200
MIXED_SEEDS = (0, 1)
SIZES = (5, 20, 50, 100, 200)
QUICK_SIZES = (5, 20)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="N = 5 and 20 only")
    parser.add_argument("--sizes", type=int, nargs="*", help="the building sizes N")
    parser.add_argument(
        "--batch-max", type=int, default=51, help="largest N + 1 the batch build runs at (51)"
    )
    parser.add_argument("--one", type=int, help=argparse.SUPPRESS)  # one N, in this process
    parser.add_argument("--no-real", action="store_true", help="skip the shipped walks")
    parser.add_argument(
        "--isam",
        type=int,
        nargs="*",
        help="also time the ISAM2 engine (IsamBuilding) at these N",
    )
    parser.add_argument(
        "--isam-only", action="store_true", help="only the ISAM2 engine (with --isam)"
    )
    parser.add_argument("--isam-one", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--json", type=Path, help="also write the results here")
    args = parser.parse_args()
    if args.one is not None:
        print(json.dumps(one_size(args.one, args.batch_max)))
        return 0
    if args.isam_one is not None:
        print(json.dumps(isam_size(args.isam_one, args.batch_max)))
        return 0
    sizes = [] if args.isam_only else args.sizes or (QUICK_SIZES if args.quick else SIZES)
    rows = []
    for n in sizes:
        command = [sys.executable, __file__, "--one", str(n), "--batch-max", str(args.batch_max)]
        done = subprocess.run(command, capture_output=True, text=True, check=True)
        rows.append(json.loads(done.stdout.strip().splitlines()[-1]))
        print(f"N = {n}: done", file=sys.stderr)
    results: dict[str, Any] = {"sizes": rows}
    if rows:
        print("## Simulated buildings (CPU s; distances to the batch build of the same walks, mm)")
        print()
        print(render_markdown_table(size_table(rows), justify="right"))
        print()
    if not args.no_real and not args.isam_only:
        mixed = mixed_walks()
        results["mixed"] = mixed
        print("## Simulated walks that differ (MIXED_WALKS): the last one added to the others\n")
        print(render_markdown_table(real_table(mixed), justify="right"))
        print()
        real = real_walks()
        results["real"] = real
        print("## The mac building's shipped walks: the last one added to the others\n")
        print(render_markdown_table(real_table(real), justify="right"))
    if args.isam:
        isam_rows = []
        for n in args.isam:
            command = [
                sys.executable, __file__, "--isam-one", str(n), "--batch-max", str(args.batch_max)
            ]  # fmt: skip
            done = subprocess.run(command, capture_output=True, text=True, check=True)
            isam_rows.append(json.loads(done.stdout.strip().splitlines()[-1]))
            print(f"ISAM2 N = {n}: done", file=sys.stderr)
        results["isam"] = isam_rows
        print("\n## The ISAM2 engine (IsamBuilding; CPU s; distances to the batch build, mm)\n")
        print(render_markdown_table(isam_table(isam_rows), justify="right"))
        if not args.no_real:
            results["isam_mixed"] = mixed_walks("isam")
            results["isam_real"] = real_walks("isam")
            for title, key in (("MIXED_WALKS", "isam_mixed"), ("the mac walks", "isam_real")):
                print(f"\n## The ISAM2 engine on {title}: the last one added to the others\n")
                print(render_markdown_table(real_table(results[key]), justify="right"))
    if args.json:
        args.json.write_text(json.dumps(results, indent=2))
    return 0


def one_size(n: int, batch_max: int) -> dict[str, Any]:
    params = SlamParams()
    building = simulate_building_sessions(
        SimulationConfig(num_poses=SIMULATED_POSES, seed=7), count=n + 1
    )
    walks = [
        Walk(walk_id=f"walk {k + 1}", session=parse_session(s.upload))
        for k, s in enumerate(building.sessions)
    ]
    by_id = {w.walk_id: w.session for w in walks}
    started = time.process_time()
    optimize_session(walks[-1].session, params)
    single_s = time.process_time() - started

    started = time.process_time()
    state, built = build(walks[:n], params)
    build_s = time.process_time() - started
    started = time.process_time()
    added_state, added = add_walk(state, walks[n], params, load=by_id.__getitem__)
    add_s = time.process_time() - started
    started = time.process_time()
    _, removed = remove_walk(added_state, walks[n].walk_id, params, load=by_id.__getitem__)
    remove_s = time.process_time() - started
    peak_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    rows = [added_state.to_dict(), *(w.to_dict() for w in added_state.walks)]
    state_mib = sum(len(r["arrays"]) + len(json.dumps({**r, "arrays": ""})) for r in rows) / 2**20
    out: dict[str, Any] = {
        "n": n,
        "tags": len(added_state.tag_ids),
        "single_s": single_s,
        "build_s": build_s,
        "add_s": add_s,
        "remove_s": remove_s,
        "build_relinearized": len(built.relinearized),
        "add_relinearized": len(added.relinearized),
        "remove_relinearized": len(removed.relinearized),
        "add_rounds": added.rounds,
        "add_timings_ms": added.timings_ms,
        "remove_timings_ms": removed.timings_ms,
        "peak_mib": peak_mib,
        "state_mib": state_mib,
    }
    if n + 1 <= batch_max:
        out.update(against_the_batch(walks, n, params, build=built, add=added, remove=removed))
    return out


def against_the_batch(
    walks: list[Walk],
    n: int,
    params: SlamParams,
    **served: IncrementalMap,
) -> dict[str, Any]:
    """The batch build of the first ``n`` walks and, warm, of all of them (CPU s), and how far
    each map of ``served`` is from its batch map, mm (``add``: all the walks'; ``build``,
    ``remove``, ``restore``: the first ``n`` walks')."""
    sessions = [w.session for w in walks]
    names = [w.walk_id for w in walks]
    out: dict[str, Any] = {}
    started = time.process_time()
    before = optimize_sessions(sessions[:n], params, names=names[:n])
    out["batch_build_s"] = time.process_time() - started
    started = time.process_time()
    after = optimize_sessions(sessions, params, names=names, initial=before)
    out["batch_add_s"] = time.process_time() - started
    for name, map_ in served.items():
        out[f"{name}_diff_mm"] = differences_mm(map_, after if name == "add" else before)
    out["batch_features"] = batch_features(after)
    return out


def differences_mm(served: IncrementalMap, joint: JointMap) -> list[float]:
    """The largest tag and pose position distances between the served map and the batch map,
    mm (both in the first walk's world)."""
    return [1e3 * d for d in served.largest_differences_m(joint)]


def batch_features(joint: JointMap) -> str:
    """What the batch build did that the summaries do not: down-weighting, rescaling, split tags."""
    notes = []
    weighted = [p for p in joint.parts if p.disagreement_factor > 1.0]
    if weighted:
        notes.append(
            "weights " + ", ".join(f"{p.dataset} ×{p.disagreement_factor:.3g}" for p in weighted)
        )
    scaled = [p for p in joint.parts if p.alignment.odometry_scale != 1.0]
    if scaled:
        notes.append(
            "scales " + ", ".join(f"{p.dataset} ×{p.alignment.odometry_scale:.4f}" for p in scaled)
        )
    split = [p for p in joint.parts if p.local_tags]
    if split:
        notes.append("split " + ", ".join(f"{p.dataset} {list(p.local_tags)}" for p in split))
    return "; ".join(notes) or "none"


def size_table(rows: Sequence[dict[str, Any]]) -> list[list[str]]:
    lines = [
        ["N", "tags", "single walk s", "first build s", "add s (relin.)", "remove s (relin.)",
         "peak MiB", "state MiB", "batch build s", "batch add s", "build Δ tag/pose",
         "add Δ tag/pose", "remove Δ tag/pose", "batch did"],
    ]  # fmt: skip
    for r in rows:

        def diff(key: str, r: dict[str, Any] = r) -> str:
            return f"{r[key][0]:.2f} / {r[key][1]:.1f}" if key in r else "—"

        lines.append(
            [
                str(r["n"]),
                str(r["tags"]),
                f"{r['single_s']:.2f}",
                f"{r['build_s']:.1f}",
                f"{r['add_s']:.2f} ({r['add_relinearized']})",
                f"{r['remove_s']:.2f} ({r['remove_relinearized']})",
                f"{r['peak_mib']:.0f}",
                f"{r['state_mib']:.1f}",
                f"{r['batch_build_s']:.1f}" if "batch_build_s" in r else "not run",
                f"{r['batch_add_s']:.1f}" if "batch_add_s" in r else "not run",
                diff("build_diff_mm"),
                diff("add_diff_mm"),
                diff("remove_diff_mm"),
                str(r.get("batch_features", "—")),
            ]
        )
    return lines


def real_walks(engine: str = "summaries") -> list[dict[str, Any]]:
    present = [name for name in MAC_WALKS if (SESSIONS / f"{name}.json").exists()]
    sessions: dict[str, Session] = {n: load_session(SESSIONS / f"{n}.json") for n in present}
    return added_last([Walk(walk_id=n, session=s) for n, s in sessions.items()], engine=engine)


def mixed_walks(engine: str = "summaries") -> list[dict[str, Any]]:
    """Issue 25's building (as configured, 3× noisier, odometry +2%, oblique) and a fifth walk as
    configured: the batch build down-weights and rescales there."""
    out = []
    for seed in MIXED_SEEDS:
        building = simulate_building_sessions(
            SimulationConfig(num_poses=SIMULATED_POSES, seed=seed), count=5, styles=MIXED_WALKS
        )
        walks = [
            Walk(walk_id=f"seed {seed}: {style.label}", session=parse_session(s.upload))
            for s, style in zip(building.sessions, building.styles, strict=True)
        ]
        walks[-1] = Walk(walk_id=f"seed {seed}: fifth", session=walks[-1].session)
        out.extend(added_last(walks, only_last=True, engine=engine))
    return out


def added_last(
    walks: Sequence[Walk], *, only_last: bool = False, engine: str = "summaries"
) -> list[dict[str, Any]]:
    """For each k ≥ 2 (only the last with ``only_last``): walks[:k] built, walks[k] added
    (``engine``: "summaries" or "isam", whose "relinearized" is its ISAM2 updates), against the
    batch build of walks[:k + 1] with and without its down-weighting."""
    params = SlamParams()
    sessions = {w.walk_id: w.session for w in walks}
    out = []
    for last in [len(walks) - 1] if only_last else range(2, len(walks)):
        started = time.process_time()
        if engine == "isam":
            tree, _ = IsamBuilding.build(walks[:last], params)
            build_s = time.process_time() - started
            started = time.process_time()
            added = tree.add(walks[last])
            added = dataclasses.replace(added, relinearized=("",) * added.rounds)
        else:
            state, _ = build(walks[:last], params)
            build_s = time.process_time() - started
            started = time.process_time()
            _, added = add_walk(state, walks[last], params, load=sessions.__getitem__)
        add_s = time.process_time() - started
        names = [w.walk_id for w in walks[: last + 1]]
        chosen = [sessions[n] for n in names]
        started = time.process_time()
        batch = optimize_sessions(chosen, params, names=names)
        batch_s = time.process_time() - started
        plain = optimize_sessions(chosen, params, names=names, reweight=False)
        out.append(
            {
                "walks": names,
                "build_s": build_s,
                "add_s": add_s,
                "batch_s": batch_s,
                "relinearized": len(added.relinearized),
                "diff_mm": differences_mm(added, batch),
                "diff_unweighted_mm": differences_mm(added, plain),
                "batch_features": batch_features(batch),
                "unweighted_features": batch_features(plain),
            }
        )
    return out


def real_table(rows: Sequence[dict[str, Any]]) -> list[list[str]]:
    lines = [
        ["walks (last added)", "build s", "add s (relin.)", "batch s", "Δ tag/pose mm: batch",
         "batch did", "Δ tag/pose mm: batch without down-weighting", "it did"],
    ]  # fmt: skip
    for r in rows:
        lines.append(
            [
                " + ".join(r["walks"]),
                f"{r['build_s']:.2f}",
                f"{r['add_s']:.2f} ({r['relinearized']})",
                f"{r['batch_s']:.2f}",
                f"{r['diff_mm'][0]:.1f} / {r['diff_mm'][1]:.1f}",
                r["batch_features"],
                f"{r['diff_unweighted_mm'][0]:.1f} / {r['diff_unweighted_mm'][1]:.1f}",
                r["unweighted_features"],
            ]
        )
    return lines


def isam_size(n: int, batch_max: int) -> dict[str, Any]:
    """The ISAM2 engine (``incremental.IsamBuilding``) on the building of ``one_size``: the
    first N walks built, walk N + 1 added, taken out again, the state stored and the tree made
    again from it (a restarted worker), each in CPU s; and, for N + 1 ≤ ``batch_max``, the
    largest tag / pose distance to the batch build of the same walks after each."""
    params = SlamParams()
    building = simulate_building_sessions(
        SimulationConfig(num_poses=SIMULATED_POSES, seed=7), count=n + 1
    )
    walks = [
        Walk(walk_id=f"walk {k + 1}", session=parse_session(s.upload))
        for k, s in enumerate(building.sessions)
    ]
    del building  # its uploads (JSON): a worker holds the parsed sessions only
    started = time.process_time()
    optimize_session(walks[-1].session, params)
    single_s = time.process_time() - started
    sessions_mib = resident_mib()
    started = time.process_time()
    tree, built = IsamBuilding.build(walks[:n], params)
    build_s = time.process_time() - started
    tree_mib = resident_mib() - sessions_mib
    started = time.process_time()
    added = tree.add(walks[n])
    add_s = time.process_time() - started
    started = time.process_time()
    removed = tree.remove(walks[n].walk_id)
    remove_s = time.process_time() - started
    started = time.process_time()
    state = tree.state()
    rows = [state.to_dict(), *(w.to_dict() for w in state.walks)]
    state_s = time.process_time() - started
    del tree
    started = time.process_time()
    _, restored = IsamBuilding.restore(state, walks[:n], params)
    restore_s = time.process_time() - started
    out: dict[str, Any] = {
        "n": n,
        "tags": len(added.tag_ids),
        "single_s": single_s,
        "build_s": build_s,
        "build_timings_ms": built.timings_ms,
        "add_s": add_s,
        "add_timings_ms": added.timings_ms,
        "add_updates": added.rounds,
        "remove_s": remove_s,
        "remove_updates": removed.rounds,
        "state_s": state_s,
        "state_mib": sum(len(r["arrays"]) + len(json.dumps({**r, "arrays": ""})) for r in rows)
        / 2**20,
        "restore_s": restore_s,
        "peak_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "sessions_mib": sessions_mib,
        "tree_mib": tree_mib,
    }
    if n + 1 <= batch_max:
        out.update(
            against_the_batch(
                walks, n, params, build=built, add=added, remove=removed, restore=restored
            )
        )
    return out


def resident_mib() -> float:
    """The process's resident memory now, MiB (``VmRSS``; Linux)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def isam_table(rows: Sequence[dict[str, Any]]) -> list[list[str]]:
    lines = [
        ["N", "tags", "single walk s", "first build s", "add s (updates)",
         "remove s (updates)", "state s / MiB", "rebuild from state s",
         "peak MiB (sessions, tree)",
         "batch build s", "batch add s", "build Δ tag/pose", "add Δ tag/pose",
         "remove Δ tag/pose", "rebuilt Δ tag/pose", "batch did"],
    ]  # fmt: skip
    for r in rows:

        def diff(key: str, r: dict[str, Any] = r) -> str:
            return f"{r[key][0]:.2f} / {r[key][1]:.1f}" if key in r else "—"

        lines.append(
            [
                str(r["n"]),
                str(r["tags"]),
                f"{r['single_s']:.2f}",
                f"{r['build_s']:.1f}",
                f"{r['add_s']:.2f} ({r['add_updates']})",
                f"{r['remove_s']:.2f} ({r['remove_updates']})",
                f"{r['state_s']:.2f} / {r['state_mib']:.1f}",
                f"{r['restore_s']:.1f}",
                f"{r['peak_mib']:.0f} ({r['sessions_mib']:.0f}, {r['tree_mib']:.0f})",
                f"{r['batch_build_s']:.1f}" if "batch_build_s" in r else "not run",
                f"{r['batch_add_s']:.1f}" if "batch_add_s" in r else "not run",
                diff("build_diff_mm"),
                diff("add_diff_mm"),
                diff("remove_diff_mm"),
                diff("restore_diff_mm"),
                str(r.get("batch_features", "—")),
            ]
        )
    return lines


if __name__ == "__main__":
    raise SystemExit(main())
