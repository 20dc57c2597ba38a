"""Building maps: several mapping sessions of one building optimized together (§8, issues 15, 25).

    joint = optimize_sessions([floor_2, desnat, occam_209], SlamParams(), names=[...])
    joint.map                      # a MapResult over every session's poses and the shared tags
    joint.parts[1].alignment       # how session 1 was placed in the map before optimizing
    joint.parts[1].noise           # its noise, as its own data support it
    joint.parts[1].alone           # its own map, alone: what the report compares with
    optimize_sessions([..., new_walk], initial=joint)   # the same map, from the last optimum

The map is the optimum of one graph over all the walks, and nothing about it depends on the order
the walks are given in, nor on which walk fixes the gauge (that only says which walk's world frame
the map is drawn in: the first one's). The stages, in order, each module's docstring telling how
its step stays free of order:

model.py      the values: JointMap, SessionPart, SessionAlignment, WalkFit, AlignmentError
walks.py      1. each walk alone: its tag depth scale, its own map and its noise
alignment.py  2. two walks: one placed on the other by a turn about +y and a translation
placing.py    2. all walks placed at once; 3. each walk's candidate odometry scale
plan.py       steps 1–2 as a plan; 4. the walks concatenated into one graph's inputs
stairs.py     4. each walk's climbs from its own odometry: the variance they may add to it
              (the stairs rule, off by default) and its links between levels (the report)
scale.py      3. a candidate odometry scale kept only if it lowers the joint map's cost
weights.py    5. a tag one walk disagrees on set apart; 6. a walk its noise does not explain
              down-weighted
report.py     each walk's share of the map and the map's warnings, in sentences
solve.py      optimize_sessions: the steps in order, the graph solved until nothing changes

docs/multi-session.md explains each step and what it measured.

In a map of several sessions, a burst of k sightings of one tag (consecutive sightings less than
3 s apart) weighs as √k sightings (``screening.burst_variance_scale``), as in a map of one.
"""

from app.domain.mapping.joint.alignment import (
    ALIGNMENT_INLIER_M,
    MIN_INLIER_FRACTION,
    MIN_PAIR_BASELINE_M,
    MIN_SHARED_TAGS,
    align_session,
    observed_tag_poses,
    yaw_of,
)
from app.domain.mapping.joint.model import (
    AlignmentError,
    BoolArray,
    IntArray,
    JointMap,
    PairAlignment,
    SessionAlignment,
    SessionPart,
    WalkFit,
)
from app.domain.mapping.joint.placing import (
    MIN_ODOMETRY_SCALE_CHANGE,
    MIN_WALKS_FOR_SCALE,
    PLACEMENT_ITERATIONS,
    PLACEMENT_ROBUST_M,
    SCALE_SIGMAS,
    align_walks,
    odometry_scale_candidates,
    walk_placements,
)
from app.domain.mapping.joint.plan import (
    SESSION_GAP_S,
    JointInputs,
    JointPlan,
    ProgressCallback,
    combine_sessions,
    plan_sessions,
    prepare_joint,
)
from app.domain.mapping.joint.scale import (
    MIN_SCALE_COVERAGE,
    SCALE_TEST_QUANTILE,
    ScaleTests,
    Solved,
)
from app.domain.mapping.joint.solve import MAX_JOINT_ROUNDS, optimize_sessions
from app.domain.mapping.joint.walks import (
    MIN_DEPTH_SCALE_CHANGE,
    MIN_SCALE_PARALLAX_M2,
    SCALE_PAIR_WINDOW_S,
    fit_walk,
    keep_poses,
    scaled_tag_depths,
    sighting_burst_sizes,
    tag_depth_fit,
    tag_depth_scale,
)
from app.domain.mapping.joint.weights import (
    DISAGREEMENT_QUANTILE,
    DISAGREEMENT_TOLERANCE,
    MAX_DISAGREEMENT_FACTOR,
    PLACEMENT_DOF,
    SPLIT_QUANTILE,
)
from app.domain.mapping.screening import BURST_GAP_S, BURST_WEIGHT_POWER

__all__ = [
    "ALIGNMENT_INLIER_M",
    "BURST_GAP_S",
    "BURST_WEIGHT_POWER",
    "DISAGREEMENT_QUANTILE",
    "DISAGREEMENT_TOLERANCE",
    "MAX_DISAGREEMENT_FACTOR",
    "MAX_JOINT_ROUNDS",
    "MIN_DEPTH_SCALE_CHANGE",
    "MIN_INLIER_FRACTION",
    "MIN_ODOMETRY_SCALE_CHANGE",
    "MIN_PAIR_BASELINE_M",
    "MIN_SCALE_COVERAGE",
    "MIN_SCALE_PARALLAX_M2",
    "MIN_SHARED_TAGS",
    "MIN_WALKS_FOR_SCALE",
    "PLACEMENT_DOF",
    "PLACEMENT_ITERATIONS",
    "PLACEMENT_ROBUST_M",
    "SCALE_PAIR_WINDOW_S",
    "SCALE_SIGMAS",
    "SCALE_TEST_QUANTILE",
    "SESSION_GAP_S",
    "SPLIT_QUANTILE",
    "AlignmentError",
    "BoolArray",
    "IntArray",
    "JointInputs",
    "JointMap",
    "JointPlan",
    "PairAlignment",
    "ProgressCallback",
    "ScaleTests",
    "SessionAlignment",
    "SessionPart",
    "Solved",
    "WalkFit",
    "align_session",
    "align_walks",
    "combine_sessions",
    "fit_walk",
    "keep_poses",
    "observed_tag_poses",
    "odometry_scale_candidates",
    "optimize_sessions",
    "plan_sessions",
    "prepare_joint",
    "scaled_tag_depths",
    "sighting_burst_sizes",
    "tag_depth_fit",
    "tag_depth_scale",
    "walk_placements",
    "yaw_of",
]
