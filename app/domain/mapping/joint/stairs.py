"""Odometry trusted stretch by stretch: a walk's stairs held by what they climb, not how long.

    climbs = walk_climbs(session)                  # where the walk changes floor (its own odometry)
    added = stairs_variance(session, params)       # (N, 2) variance the stairs add to the odometry
    GraphInputs(..., odometry_added_variance=added)

A building map joins its floors through each walk's odometry on the stairs (issue 37). The model
gives a walk's odometry one random-walk rate, so the variance of a stretch grows with its
duration: of two walks, the one that saw a tag just before and just after the stairs holds the
link between the floors firmly, the one whose sightings on the stairs were rejected (or that saw
no tag on the landing) loosely, whatever each odometry did on the stairs. Real odometry errs on
the stairs by the flight, not by the second: the real walks' stair stretches err by 2.4–5.4 σ of
the time-based model, 0–3.7° in heading per flight pair, on stretches of 10–35 s
(bench/regions.py, table 2). So a building map can add to each odometry step a variance in
proportion to the height the walk climbed or descended over it: ``stairs_yaw_var_rad2_per_m``
to its rotation, ``stairs_linear_var_m2_per_m`` to its translation (per axis). Each flight then
weighs the same in every walk, and a walk's odometry off the stairs is trusted as before. Off by
default (both 0): it makes simulated pairs of walks better on average, not the real pair it was
meant for (bench/stairs_rule.py; docs/multi-session.md says why no rule without a reference can
choose between two walks' links).

Whether on or off, the report says how much each walk's odometry decides where one level sits
against another (:func:`stair_link_trust`: ``SessionPart.stair_links`` and its ``weighting``).

The climb is the walk's own odometry height (ARKit's y, gravity-aligned), never the truth's:
averaged over ``CLIMB_SMOOTHING_S`` (a phone raised toward a tag and lowered again is not a
floor change), a step counts where that height changes faster than ``CLIMB_MIN_SPEED_M_PER_S``,
in runs that change it by at least ``MIN_CLIMB_M`` (a flight of stairs). The constants come from
the shipped real walks' heights alone (no ground truth; docs/multi-session.md).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from app.domain.frames import FloatArray
from app.domain.mapping.params import SlamParams
from app.domain.upload.session import Session

#: The height is averaged over this window (centred) before it is differentiated, s: on the
#: shipped single-floor walks, a phone raised toward a tag moves 0.1–0.2 m/s for a second or two.
CLIMB_SMOOTHING_S = 6.0
#: A step climbs where the averaged height changes faster than this, m/s (the real stairs:
#: 0.2–0.35 m/s; the single-floor walks stay under 0.14 m/s once averaged).
CLIMB_MIN_SPEED_M_PER_S = 0.12
#: … in a run of such steps whose height changes by at least this, m (a flight of stairs).
MIN_CLIMB_M = 1.0


@dataclass(frozen=True, slots=True, kw_only=True)
class Climb:
    """A stretch where a walk changes height (stairs, a ramp, a lift), from its own odometry.

    first_pose, stop_pose: the walk's pose rows it spans (stop exclusive).
    height_m: net height change (+ up), m; climbed_m: height climbed or descended, m (the
        averaged height's |Δ| summed: what the stairs variance is proportional to).
    duration_s: its duration, s.
    """

    first_pose: int
    stop_pose: int
    height_m: float
    climbed_m: float
    duration_s: float


def averaged_height_m(session: Session) -> FloatArray:
    """(N,) the odometry's height averaged over ``CLIMB_SMOOTHING_S`` (centred), m."""
    height_m = session.world_T_phone[:, 1, 3]
    times_s = session.timestamp_s
    if len(times_s) == 0:
        return np.zeros(0)
    half_s = CLIMB_SMOOTHING_S / 2
    lo = np.searchsorted(times_s, times_s - half_s, side="left")
    hi = np.searchsorted(times_s, times_s + half_s, side="right")
    summed = np.concatenate([[0.0], np.cumsum(height_m)])
    return np.asarray((summed[hi] - summed[lo]) / (hi - lo), dtype=np.float64)


def walk_climbs(session: Session) -> list[Climb]:
    """The stretches where ``session`` climbs or descends (module docstring), in time order."""
    if session.num_poses < 2:
        return []
    height_m = averaged_height_m(session)
    step_m = np.diff(height_m)
    dt_s = np.maximum(np.diff(session.timestamp_s), 1e-6)
    climbing = np.abs(step_m) / dt_s > CLIMB_MIN_SPEED_M_PER_S
    edges = np.flatnonzero(np.diff(np.concatenate([[0], climbing.astype(np.int8), [0]])))
    out = []
    for start, stop in zip(edges[::2].tolist(), edges[1::2].tolist(), strict=True):
        net_m = float(height_m[stop] - height_m[start])
        if abs(net_m) < MIN_CLIMB_M:
            continue
        out.append(
            Climb(
                first_pose=start,
                stop_pose=stop + 1,
                height_m=net_m,
                climbed_m=float(np.abs(step_m[start:stop]).sum()),
                duration_s=float(session.timestamp_s[stop] - session.timestamp_s[start]),
            )
        )
    return out


def climb_per_step_m(session: Session, climbs: Sequence[Climb] | None = None) -> FloatArray:
    """(N,) the height climbed or descended from pose i to pose i + 1 on the walk's climbs, m
    (0 elsewhere, and for the last pose)."""
    out = np.zeros(session.num_poses)
    if session.num_poses < 2:
        return out
    step_m = np.abs(np.diff(averaged_height_m(session)))
    for climb in walk_climbs(session) if climbs is None else climbs:
        out[climb.first_pose : climb.stop_pose - 1] = step_m[climb.first_pose : climb.stop_pose - 1]
    return out


def stairs_on(params: SlamParams) -> bool:
    return params.stairs_yaw_var_rad2_per_m > 0 or params.stairs_linear_var_m2_per_m > 0


def stairs_variance(
    session: Session, params: SlamParams, climbs: Sequence[Climb] | None = None
) -> FloatArray:
    """(N, 2) the variance the walk's climbs add to its odometry from pose i to pose i + 1:
    translation (m², per axis) and rotation (rad², per axis), ``params``' rates per metre
    climbed (``GraphInputs.odometry_added_variance``)."""
    climbed_m = climb_per_step_m(session, climbs)
    return np.stack(
        [
            params.stairs_linear_var_m2_per_m * climbed_m,
            params.stairs_yaw_var_rad2_per_m * climbed_m,
        ],
        axis=1,
    )


#: Two tags whose heights in the map differ by more than this, with no tag between, are on
#: different levels (floors, or a stair landing), m.
LEVEL_GAP_M = 1.5


def tag_levels(world_T_tag: Mapping[int, FloatArray]) -> dict[int, int]:
    """Each tag's level (0 the lowest) from its height in the map: a new level where two
    consecutive heights are more than ``LEVEL_GAP_M`` apart (a landing's tag is a level)."""
    ids = sorted(world_T_tag, key=lambda t: float(world_T_tag[t][1, 3]))
    levels, level = {}, 0
    for previous, t in zip([None, *ids[:-1]], ids, strict=True):
        if (
            previous is not None
            and world_T_tag[t][1, 3] - world_T_tag[previous][1, 3] > LEVEL_GAP_M
        ):
            level += 1
        levels[t] = level
    return levels


@dataclass(frozen=True, slots=True, kw_only=True)
class StairLink:
    """A stretch of a walk that only its odometry carries from one level to another: from its
    last sighting of a tag on one level to its next of a tag on another (the stairs between two
    floors), and how much the map trusts it.

    first_pose, stop_pose: the walk's pose rows (stop exclusive); levels: the two levels
        (``tag_levels``, lower first); duration_s: its duration, s; climbed_m: height its
        odometry climbed or descended on it (``walk_climbs``), m.
    sigma_yaw_time_rad: σ of its heading by the walk's rate alone (rate × duration), rad;
        sigma_yaw_rad: with the stairs' variance (what the map used), rad.
    share, share_by_time: its share of the information on the heading between these two levels
        over every walk's links between them (1/σ² over the sum), with the stairs' variance and by
        time alone.
    """

    first_pose: int
    stop_pose: int
    levels: tuple[int, int]
    duration_s: float
    climbed_m: float
    sigma_yaw_time_rad: float
    sigma_yaw_rad: float
    share: float = math.nan
    share_by_time: float = math.nan


def stair_links(
    session: Session,
    used: npt.NDArray[np.bool_],
    levels: Mapping[int, int],
    climbs: Sequence[Climb],
) -> list[tuple[int, int, tuple[int, int], float]]:
    """Where ``session`` goes from a tag on one level to a tag on another between two
    consecutive used sightings (of tags with a level): (first pose, stop pose, the two levels
    lower first, metres climbed), in time order."""
    d = session.detections
    rows = np.flatnonzero(used & np.isin(d.tag_id, list(levels)))
    rows = rows[np.argsort(d.timestamp_s[rows], kind="stable")]
    climbed_m = np.concatenate([[0.0], np.cumsum(climb_per_step_m(session, climbs))])
    out = []
    for a, b in itertools.pairwise(rows.tolist()):
        level_a, level_b = levels[int(d.tag_id[a])], levels[int(d.tag_id[b])]
        if level_a == level_b:
            continue
        first, last = int(d.pose_index[a]), int(d.pose_index[b])
        pair = (min(level_a, level_b), max(level_a, level_b))
        out.append((first, last + 1, pair, float(climbed_m[last] - climbed_m[first])))
    return out


def stair_link_trust(
    sessions: Sequence[Session],
    used: Sequence[npt.NDArray[np.bool_]],
    levels: Mapping[int, int],
    climbs: Sequence[Sequence[Climb]],
    params: SlamParams,
    angular_scales: FloatArray,
) -> list[list[StairLink]]:
    """Each walk's links between levels (:func:`stair_links`) with the σ of heading the map gave
    them: walk ``s``'s angular rate × ``angular_scales[s]`` over the link's duration, plus the
    stairs' variance over what it climbed; and each link's share over all walks' links between
    the same two levels."""
    rows: list[list[tuple[int, int, tuple[int, int], float, float, float, float]]] = []
    for s, session in enumerate(sessions):
        rate = params.odom_angular_var_rad2_per_s * float(angular_scales[s])
        walk = []
        for first, stop, pair, climbed_m in stair_links(session, used[s], levels, climbs[s]):
            duration_s = float(session.timestamp_s[stop - 1] - session.timestamp_s[first])
            by_time = max(rate * duration_s, 1e-12)
            variance = by_time + params.stairs_yaw_var_rad2_per_m * climbed_m
            walk.append((first, stop, pair, duration_s, climbed_m, by_time, variance))
        rows.append(walk)
    by_time_total: dict[tuple[int, int], float] = {}
    total: dict[tuple[int, int], float] = {}
    for r in (r for walk in rows for r in walk):
        by_time_total[r[2]] = by_time_total.get(r[2], 0.0) + 1.0 / r[5]
        total[r[2]] = total.get(r[2], 0.0) + 1.0 / r[6]
    return [
        [
            StairLink(
                first_pose=first,
                stop_pose=stop,
                levels=pair,
                duration_s=duration_s,
                climbed_m=climbed_m,
                sigma_yaw_time_rad=math.sqrt(by_time),
                sigma_yaw_rad=math.sqrt(variance),
                share=1.0 / variance / total[pair],
                share_by_time=1.0 / by_time / by_time_total[pair],
            )
            for first, stop, pair, duration_s, climbed_m, by_time, variance in walk
        ]
        for walk in rows
    ]
