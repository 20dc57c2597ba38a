"""Building maps that grow a walk at a time (§10, issue 38): two designs, measured.

Status: a domain engine whose state every batch build of several walks stores with its version
(``from_batch.py``, ``app.storage.isam_states``) and which, with
``INVISIBLE_MAP_INCREMENTAL_BUILDS``, the worker uses for a change of one walk (``changes.py``)
and serves as the batch build's ``JointMap`` where the batch build's later steps would change
no walk (``served_map.py``); docs/multi-session.md, "Incremental building maps", says what is
left.

**gtsam's ISAM2 on the batch build's joint graph** (``isam.py``, the engine the worker uses): each
walk's factors are those of its chain in the batch graph, known by their indices in the tree, so
an add puts one walk's factors in and a removal takes them out (ISAM2 drops the variables left
without factors), and the tree is updated until it relinearizes nothing. Its graph is the batch
build's, so its optimum is the batch map where the batch build keeps every walk as it is (no
odometry rescaled, no tag set apart, no walk down-weighted: those it does not redo yet). The
tree cannot be stored; what makes it can, as data (``isam_state.py``): each walk's fit (depth
scale, noise scales, cost alone), its key offset, placement and optimized keyframes, and the
tags; a restarted worker makes the tree again from them and the sessions in one elimination.
Measured (``.venv/bin/python bench/incremental.py --isam-only --isam 5 20 50 100 200``; CPU s,
simulated walks of 1,200 poses, seed 7):

    walks   first build   add one   remove one   rebuild from state   Δ to batch, tags / poses
       20         2.8       0.38        0.17            0.3               0.02 / 0.3 mm
       50         6.2       0.37        0.14            0.5               0.08 / 7.7 mm
      100        12.7       0.38        0.16            1.0               (batch not run)
      200        41.7       1.03        0.59            2.3               (batch not run)

(peak 1,105 MiB at 200, the simulation's included; docs/multi-session.md has the whole table.)

    building, served = IsamBuilding.build(walks, params)
    served = building.add(Walk(walk_id="w9", session=s9))
    served = building.remove("w3")
    state = building.state()                      # rows: state.to_dict(), w.to_dict()
    building, served = IsamBuilding.restore(state, walks, params)   # StaleStateError: rebuild

**Each walk condensed to a summary factor on its tags** (``summary.py``, ``building.py``,
``updates.py``): within millimetres of the batch build on uniform simulated walks, but not on
mixed ones (a walk whose odometry scale the batch corrects) nor on the real mac walks, where the
relinearization loop does not converge (3 m off the batch with desnat_straight_once): a summary
holds a walk's curvature only near where it was made, and the loop has no outer check of the
walks' true cost. The fingerprints of ``state.py`` serve both designs.

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

isam.py        IsamBuilding: the building map in an ISAM2 tree (build, add, remove, restore)
isam_state.py  IsamState, IsamWalkState: what makes the tree again, as rows
from_batch.py  state_from_batch: the state of a batch build's optimum, no solve
changes.py     one_walk_change, apply_change: which change the engine makes from a stored state
served_map.py  served_joint_map: the engine's map as the batch build's JointMap, or why not
state.py     BuildingState, WalkSummary, Walk, fingerprints, StaleStateError
summary.py   one walk's summary (gtsam: its graph linearized, its poses eliminated)
building.py  the building problem: tags and placements under the summaries
updates.py   build, add_walk, remove_walk
"""

from app.domain.mapping.incremental.building import BuildingSolution, solve_building
from app.domain.mapping.incremental.isam import MAX_UPDATES, RELINEARIZE_THRESHOLD, IsamBuilding
from app.domain.mapping.incremental.isam_state import (
    ISAM_STATE_FORMAT,
    IsamState,
    IsamWalkState,
)
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
    "ISAM_STATE_FORMAT",
    "MAX_ROUNDS",
    "MAX_UPDATES",
    "RELINEARIZE_M",
    "RELINEARIZE_RAD",
    "RELINEARIZE_THRESHOLD",
    "STATE_FORMAT",
    "BuildingSolution",
    "BuildingState",
    "IncrementalMap",
    "IsamBuilding",
    "IsamState",
    "IsamWalkState",
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
