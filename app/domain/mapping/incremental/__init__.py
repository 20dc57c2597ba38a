"""Building maps that grow a walk at a time (§10, issue 38).

Status: a measured design, not yet what the worker serves. It matches the batch build within
millimetres on uniform simulated walks (bench/incremental.py), but not on mixed ones (a walk whose
odometry scale the batch corrects) nor on the real mac walks, where the relinearization loop does
not converge (3 m off the batch with desnat_straight_once): a summary holds a walk's curvature
only near where it was made, and the loop has no outer check of the walks' true cost. The same
bench measures gtsam's ISAM2 on the batch graph (``--isam N``), the engine to wire in next; the
fingerprints and row layout of ``state.py`` carry over to it.

    state, served = build(walks, params)                          # from scratch
    state, served = add_walk(state, Walk(walk_id="w9", session=s), params, load=by_id)
    state, served = remove_walk(state, "w3", params, load=by_id)
    require_current(state, current_walks, params)                 # StaleStateError: rebuild
    row, walk_rows = state.to_dict(), [w.to_dict() for w in state.walks]

Each walk is condensed to a *summary*: its pose chain marginalized at the poses that fit its tags
best, a Gaussian on its tags in its own world frame (``summary.py``). The building is then only
tags and placements (``building.py``), and a change re-solves that and relinearizes only the walks
whose tags moved (``updates.py``). The state is plain data (``state.py``): one row per map
version, one per walk.

What it reproduces of the batch build (``joint.optimize_sessions``), exactly at its optimum: each
walk's screening, tag depth scale, keyframes, bursts, noise estimated from its own residuals
(the same ``WalkFit``), gravity (inside each summary; a placement turns about +y only), the Huber
kernel (its weights are those at the walk's linearization point, updated when it is
relinearized), the gauge (the first walk's world). What it does not (``updates.py`` says how far
that takes it from the batch map, bench/incremental.py measures it): the odometry scale tests
(step 3), tags set apart (step 5) and walks down-weighted for their disagreement (step 6); and
each walk's first pose keeps its tilt prior (1 / rad², against gravity's ~10⁴ per keyframe),
which the batch graph has on the first walk's only.

state.py     BuildingState, WalkSummary, Walk, fingerprints, StaleStateError
summary.py   one walk's summary (gtsam: its graph linearized, its poses eliminated)
building.py  the building problem: tags and placements under the summaries
updates.py   build, add_walk, remove_walk
"""

from app.domain.mapping.incremental.building import BuildingSolution, solve_building
from app.domain.mapping.incremental.state import (
    STATE_FORMAT,
    BuildingState,
    StaleStateError,
    Walk,
    WalkSummary,
    building_fingerprint,
    require_current,
    walk_fingerprint,
)
from app.domain.mapping.incremental.summary import summarize_walk
from app.domain.mapping.incremental.updates import (
    MAX_ROUNDS,
    RELINEARIZE_M,
    RELINEARIZE_RAD,
    IncrementalMap,
    SessionLoader,
    add_walk,
    build,
    remove_walk,
)

__all__ = [
    "MAX_ROUNDS",
    "RELINEARIZE_M",
    "RELINEARIZE_RAD",
    "STATE_FORMAT",
    "BuildingSolution",
    "BuildingState",
    "IncrementalMap",
    "SessionLoader",
    "StaleStateError",
    "Walk",
    "WalkSummary",
    "add_walk",
    "build",
    "building_fingerprint",
    "remove_walk",
    "require_current",
    "solve_building",
    "summarize_walk",
    "walk_fingerprint",
]
