"""Reference corridor graph of floor 2 of the mac building (issue 18), drawn by hand.

Frame: the ground truth's y-up frame (``data/ground_truth/rtabmap_mac_1_2.txt`` as
``app.domain.evaluation.ground_truth`` reads it); points are (x, z), m; floor 2 is at y ≈ 0.

How it was drawn: the three sessions that walk floor 2 (floor_2_straight, desnat_straight_once and
the floor-2 part of straight_209_occam) were optimized with default parameters, each aligned to
the ground truth by a rigid fit on its tags (``umeyama_rigid``; tag residuals 0.1–0.9 m), and
plotted over the ground-truth tags on a 1 m grid. The ground-truth tags are on the walls, so a
corridor's centreline runs midway between tags facing each other (e.g. 303/302, 305/304) and
beside lone ones; where the walks run side by side, the line follows their middle; where the
walks bend the same way at the same place, that is a corner. A short dead end where every walk
turned round at a tag (301, 316, 303 …) is the walker stepping to the wall, not a corridor; a
branch is a corridor only when a walk goes at least 4 m along it (the spur east of 307 towards
(−2, 37), the spur north-east of 313 towards 314, and the alcove north of 319 to tag 318). The
stairs down to floor 1 (south of 303, straight_209_occam) are not part of this floor's graph.
"""

from __future__ import annotations

import itertools

import networkx as nx
import numpy as np

from app.domain.navigation.floors import find_floor_levels
from app.domain.navigation.path_graph import JUNCTION, NODE, WALK, PathGraph
from app.domain.navigation.skeleton import attach_anchor

# fmt: off
#: The main corridor, south (tag 300) to north-west (tag 324), (x, z) m.
MAIN = [
    (0.3, 0.9), (-1.2, 4.5), (-1.6, 10.0), (-2.2, 14.5), (-3.0, 18.0), (-5.3, 27.0),
    (-6.6, 30.3), (-9.0, 34.5), (-11.6, 40.6), (-13.0, 42.0), (-15.8, 46.5), (-19.5, 50.5),
    (-20.8, 52.8), (-25.5, 55.8), (-29.5, 58.4), (-30.0, 61.6), (-31.5, 61.5), (-33.0, 61.6),
    (-35.0, 62.8), (-38.0, 65.0), (-40.8, 68.8), (-43.0, 69.2), (-47.0, 71.0), (-52.0, 73.0),
    (-52.8, 75.0), (-52.6, 77.5), (-51.5, 78.8),
]
#: Spurs, each from a point of the main corridor.
SPURS = [
    [(-6.6, 30.3), (-4.5, 31.6), (-2.5, 33.0), (-2.2, 37.5)],  # east of 307
    [(-30.0, 61.6), (-28.0, 65.0)],                              # north-east, towards 314
    [(-40.8, 68.8), (-40.4, 72.3)],                              # the alcove of 318
]
# fmt: on
#: Where the stairs down to floor 1 leave the corridor (a branch point of the floor, though the
#: stairs themselves are not drawn): south-west of 303, where straight_209_occam starts down.
STAIRS_TOP_XZ = (-4.6, 13.5)
#: Height of floor 2 in this frame, m (the ground-truth tags of the floor are at −0.2 … 0.3).
FLOOR_2_Y_M = 0.0
#: A ground-truth tag farther than this from the reference corridors is not on them, m.
TAG_MAX_DISTANCE_M = 3.0


def reference_graph(gt_positions_m: dict[int, tuple[float, float, float]]) -> PathGraph:
    """The reference as a :class:`PathGraph` (one floor), with the ground-truth tags of floor 2
    within ``TAG_MAX_DISTANCE_M`` attached."""
    G: nx.Graph[int] = nx.Graph()
    ids: dict[tuple[float, float], int] = {}

    def node(xz: tuple[float, float]) -> int:
        if xz not in ids:
            ids[xz] = len(ids)
            G.add_node(
                ids[xz],
                position_m=(xz[0], FLOOR_2_Y_M, xz[1]),
                floor=0,
                kind=NODE,
                pose_index=None,
            )
        return ids[xz]

    for line in (MAIN, *SPURS):
        for a, b in itertools.pairwise(line):
            G.add_edge(
                node(a),
                node(b),
                length_m=float(np.hypot(a[0] - b[0], a[1] - b[1])),
                kind=WALK,
                floor=0,
            )
    for n in G.nodes:
        if G.degree(n) >= 3:
            G.nodes[n]["kind"] = JUNCTION
    levels = find_floor_levels(np.array([FLOOR_2_Y_M]))
    tags = {}
    for tag, p in sorted(gt_positions_m.items()):
        if abs(p[1] - FLOOR_2_Y_M) > 1.5:
            continue
        if _distance_to_lines((p[0], p[2])) > TAG_MAX_DISTANCE_M:
            continue
        tags[tag] = attach_anchor(G, str(tag), np.asarray(p, dtype=np.float64), levels)
    return PathGraph(graph=G, floor_levels_m=(FLOOR_2_Y_M,), tags=tags)


def branch_points_xz() -> list[tuple[float, float]]:
    """The reference's branch points (x, z), m: where the spurs leave and the stairs' head."""
    return [s[0] for s in SPURS] + [STAIRS_TOP_XZ]


def _distance_to_lines(xz: tuple[float, float]) -> float:
    best = float("inf")
    p = np.asarray(xz)
    for line in (MAIN, *SPURS):
        for a, b in itertools.pairwise(line):
            a_, b_ = np.asarray(a), np.asarray(b)
            ab = b_ - a_
            t = float(np.clip((p - a_) @ ab / (ab @ ab), 0.0, 1.0))
            best = min(best, float(np.linalg.norm(p - (a_ + t * ab))))
    return best
