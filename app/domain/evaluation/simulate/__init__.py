"""Synthetic mapping sessions in the app's upload format (architecture §2), with known truth.

    sim = simulate_session(SimulationConfig(num_poses=1_000))          # realistic ARKit-like noise
    sim = simulate_session(SimulationConfig(num_poses=1_000).without_noise())
    session = parse_session(sim.upload)           # a JSON-ready dict, as the app uploads it
    sim.world_T_phone_true, sim.world_T_tag_true  # the truth a SLAM result is scored against
    sim.ground_truth_json()                       # {"poses": [{"tag_id", "pose": xyz + quat_xyzw}]}

The world: a procedural building, a grid of corridors (``blocks`` × ``block_size_m``; the default
is a 30 m × 20 m loop with a middle corridor, so two loops), optionally a second floor reached by a
switch-back staircase. AprilTags hang on the corridor walls every ``tag_spacing_m`` (random) along
each corridor, 1.2–1.6 m high, +z out of the wall into the corridor and +y up.

The walk: along corridor centrelines at constant speed, always taking the least-walked corridor at
a junction (random tie-break, no U-turns), so corridors are covered and tags revisited (loop
closures); with two floors, half the walk (at most one floor's worth at a time) on each floor. The
phone is held in front at about 1.3 m, looking along the walking direction, swinging left and
right, and turned toward the tag ahead while the walker pays attention (70% of the time).

The noise (each from its own random stream, so changing one noise level changes nothing else; the
building, the walk and *which* detections happen never depend on the noise, so a config and its
``without_noise()`` twin share their truth and detection list):

- odometry = the true trajectory corrupted by an accumulating drift that is zero at the start: a
  heading random walk about the gravity axis, a translation random walk, and a small *bounded*
  roll/pitch error (ARKit observes gravity, so tilt does not drift);
- a tag measurement is relative to the TRUE phone pose plus its own noise: position noise growing
  with distance and larger along the line of sight, rotation noise growing with the view angle,
  and optional gross outliers. That independence is what lets SLAM fix the drift.

Error sources of real walks that white noise does not have (issue 37), each switchable and off by
default (:data:`REGION_ERROR_SOURCES` holds them with the real figures they reproduce): odometry
that errs in a few stretches (the stairs, fast turns) rather than evenly, walks that change floor
only once, walkers who glance at a tag for two or three sightings, and a sighting bias that
persists through one approach to a tag.

The stages, a module each (the package re-exports what other code imports):

config.py         SimulationConfig, the array types, the walker/phone/building/detector constants
                  and issue 37's error sources (REGION_ERROR_SOURCES, REAL_WALK_SOURCES)
building.py       Building, build_building: the corridor grid, its staircase, free space and tags
walk.py           walk_route: the true phone trajectory (route, gait, sway, where the phone looks)
odometry.py       drift_odometry, stairs_traversals: the drift and the stairs/fast-turn errors
detections.py     visible_pairs, approach_ids, measure_detections: what the camera sees, measured
upload.py         points_of_interest_of, upload_document: the app's upload document
session.py        SimulatedSession, simulate_session, record_walk, simulate_along_trajectory
numeric.py        small helpers: smoothing, smooth noise, rotations about one axis
walkers.py        WalkerConfig, UNSEEN_BUILDING, UNSEEN_WALKERS, SimulatedWalk, simulate_walk,
                  walks_of_one_building: walkers who stray as real mappers do (issue 18)
walker_graphs.py  corridor_graph, fused_skeleton: the reference and the skeleton of such walks
"""

from __future__ import annotations

from app.domain.evaluation.simulate.building import Building, build_building
from app.domain.evaluation.simulate.config import (
    APPROACH_GAP_S,
    POI_NAMES,
    REAL_WALK_SOURCES,
    REGION_ERROR_SOURCES,
    START_TIME_S,
    BoolArray,
    IntArray,
    SimulationConfig,
)
from app.domain.evaluation.simulate.detections import (
    approach_ids,
    measure_detections,
    visible_pairs,
)
from app.domain.evaluation.simulate.odometry import drift_odometry, stairs_traversals
from app.domain.evaluation.simulate.session import (
    SimulatedSession,
    record_walk,
    simulate_along_trajectory,
    simulate_session,
)
from app.domain.evaluation.simulate.upload import points_of_interest_of, upload_document
from app.domain.evaluation.simulate.walk import walk_route
from app.domain.evaluation.simulate.walker_graphs import corridor_graph, fused_skeleton
from app.domain.evaluation.simulate.walkers import (
    UNSEEN_BUILDING,
    UNSEEN_WALKERS,
    SimulatedWalk,
    WalkerConfig,
    simulate_walk,
    walks_of_one_building,
)

__all__ = [
    "APPROACH_GAP_S",
    "POI_NAMES",
    "REAL_WALK_SOURCES",
    "REGION_ERROR_SOURCES",
    "START_TIME_S",
    "UNSEEN_BUILDING",
    "UNSEEN_WALKERS",
    "BoolArray",
    "Building",
    "IntArray",
    "SimulatedSession",
    "SimulatedWalk",
    "SimulationConfig",
    "WalkerConfig",
    "approach_ids",
    "build_building",
    "corridor_graph",
    "drift_odometry",
    "fused_skeleton",
    "measure_detections",
    "points_of_interest_of",
    "record_walk",
    "simulate_along_trajectory",
    "simulate_session",
    "simulate_walk",
    "stairs_traversals",
    "upload_document",
    "visible_pairs",
    "walk_route",
    "walks_of_one_building",
]
