"""Several simulated mapping sessions of one building, each in its own world frame (issues 15, 25).

    walks = simulate_building_sessions(SimulationConfig(num_poses=600), count=5)
    sessions = [parse_session(s.upload) for s in walks.sessions]
    walks.world_T_tag_true                      # the building's tags, building frame
    mixed = simulate_building_sessions(config, count=4, styles=MIXED_WALKS)   # walks that differ

The building comes from ``config.seed``; walk ``k`` gets its own seed (its route choices, hand
motion, odometry drift and tag noise). Every walk starts at the building's first junction, as
people entering by the same door would, and explores from there. As ARKit does, each walk's
odometry is written in a world frame of its own: gravity-aligned (+y up) but turned about +y by a
random heading and moved by a random offset from the building frame, so a map of several walks must
find how they fit together (``app.domain.mapping.joint``).

Real walks of one building differ (issue 25): one person's phone drifts more, another's odometry
runs long, a third walks past the tags without turning to them. A :class:`WalkStyle` per walk
says how its walk differs from ``config``; :data:`MIXED_WALKS` is the building of issue 25's
simulation: a walk as configured, one 3× noisier, one whose odometry is 2% too long, and one
walked obliquely to the tags.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from app.domain.errors import ParameterError
from app.domain.evaluation.simulate import (
    Building,
    SimulatedSession,
    SimulatedWalk,
    SimulationConfig,
    WalkerConfig,
    build_building,
    record_walk,
    simulate_walk,
)
from app.domain.frames import (
    FloatArray,
    make_pose,
    rotation_about_y,
)

#: Largest offset of a walk's world origin from the building's, per horizontal axis, m.
MAX_ORIGIN_OFFSET_M = 50.0
#: How far off the tags' normals an oblique walk may still detect them, deg (the app's detector
#: finds tags at up to ~75°; a walk that turns the phone to the tags sees them within 60°).
OBLIQUE_MAX_VIEW_ANGLE_DEG = 75.0
#: σ of the phone's yaw swing of an oblique walk: held ahead, along the corridor, rad.
OBLIQUE_LOOK_AROUND_RAD = 0.15
#: The noise fields a walk's ``noise_scale`` multiplies (σ's, so the variances grow by its square).
NOISE_FIELDS = (
    "odom_translation_drift_m_per_sqrt_s",
    "odom_vertical_drift_m_per_sqrt_s",
    "odom_rotation_drift_rad_per_sqrt_s",
    "odom_tilt_error_rad",
    "tag_position_noise_m_at_1m",
    "tag_rotation_noise_rad",
    "corner_noise_px",
)


@dataclass(frozen=True, slots=True, kw_only=True)
class WalkStyle:
    """How one walk differs from the building's ``SimulationConfig``.

        WalkStyle()                          # as configured
        WalkStyle(noise_scale=3.0)           # every noise σ 3× larger (odometry and tags)
        WalkStyle(odom_scale_error=0.02)     # odometry 2% too long (a systematic error)
        WalkStyle(oblique=True)              # the phone held ahead: tags seen in passing, obliquely

    noise_scale: multiplies every noise σ of :data:`NOISE_FIELDS`, dimensionless, > 0.
    odom_scale_error: ``SimulationConfig.odom_scale_error`` of the walk, dimensionless.
    oblique: the walker never turns the phone toward a tag (``look_at_tags`` False, a small swing)
        and the detector reports tags up to ``OBLIQUE_MAX_VIEW_ANGLE_DEG`` off their normal, where
        PnP's orientation is poorest (its noise grows as 1 / cos of the view angle).
    """

    noise_scale: float = 1.0
    odom_scale_error: float = 0.0
    oblique: bool = False

    def __post_init__(self) -> None:
        if not (math.isfinite(self.noise_scale) and self.noise_scale > 0):
            raise ParameterError(f"noise_scale must be > 0, got {self.noise_scale!r}")

    def apply(self, config: SimulationConfig) -> SimulationConfig:
        """``config`` as this walk is recorded."""
        changes: dict[str, object] = {
            name: getattr(config, name) * self.noise_scale for name in NOISE_FIELDS
        }
        changes["odom_scale_error"] = self.odom_scale_error
        if self.oblique:
            changes.update(
                look_at_tags=False,
                look_around_rad=OBLIQUE_LOOK_AROUND_RAD,
                max_view_angle_deg=OBLIQUE_MAX_VIEW_ANGLE_DEG,
            )
        return dataclasses.replace(config, **changes)  # type: ignore[arg-type]

    @property
    def label(self) -> str:
        """A short description: ``"as configured"``, ``"3× noisier"``, ``"odometry +2%"``…"""
        parts = []
        if self.noise_scale != 1.0:
            parts.append(f"{self.noise_scale:g}× noisier")
        if self.odom_scale_error:
            parts.append(f"odometry {self.odom_scale_error:+.0%}")
        if self.oblique:
            parts.append("oblique to the tags")
        return ", ".join(parts) or "as configured"


#: Issue 25's building: four walks that differ as real walks do.
MIXED_WALKS = (
    WalkStyle(),
    WalkStyle(noise_scale=3.0),
    WalkStyle(odom_scale_error=0.02),
    WalkStyle(oblique=True),
)


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class SimulatedBuilding:
    """Walks of one building. ``sessions[k].world_T_phone_true`` and ``world_T_tag_true`` are in
    the building frame; ``world_T_building[k]`` is where walk ``k``'s odometry frame puts it (the
    upload's odometry is ``world_T_building[k] @ world_T_phone_odometry``)."""

    building: Building
    sessions: tuple[SimulatedSession, ...]
    world_T_building: tuple[FloatArray, ...]
    styles: tuple[WalkStyle, ...] = ()

    @property
    def world_T_tag_true(self) -> dict[int, FloatArray]:
        return dict(self.building.world_T_tag)


def simulate_building_sessions(
    config: SimulationConfig, *, count: int, styles: Sequence[WalkStyle] = ()
) -> SimulatedBuilding:
    """``count`` walks of the building of ``config`` (see the module docstring); deterministic
    for a given config and count (walk ``k`` does not depend on ``count``). ``styles[k]`` says
    how walk ``k`` differs (walks beyond the styles given are as configured); a style changes
    how its walk is recorded, not its route choices' random draws."""
    if count < 1:
        raise ParameterError(f"count must be ≥ 1, got {count}")
    if len(styles) > count:
        raise ParameterError(f"{len(styles)} walk styles for {count} walks")
    building = build_building(
        config, np.random.default_rng(np.random.SeedSequence(config.seed).spawn(6)[0])
    )
    sessions, frames = [], []
    for k in range(count):
        style = styles[k] if k < len(styles) else WalkStyle()
        walk_config = dataclasses.replace(
            style.apply(config), seed=_walk_seed(config.seed, k), map_id=f"{config.map_id}-{k + 1}"
        )
        streams = np.random.SeedSequence(walk_config.seed).spawn(7)
        rng_walk, rng_odometry, rng_tags, rng_outliers, rng_poi, rng_frame = (
            np.random.default_rng(s) for s in streams[1:]
        )
        world_T_building = (
            np.eye(4)
            if k == 0
            else make_pose(
                rotation_about_y(float(rng_frame.uniform(-math.pi, math.pi))),
                [
                    float(rng_frame.uniform(-MAX_ORIGIN_OFFSET_M, MAX_ORIGIN_OFFSET_M)),
                    0.0,
                    float(rng_frame.uniform(-MAX_ORIGIN_OFFSET_M, MAX_ORIGIN_OFFSET_M)),
                ],
            )
        )
        sessions.append(
            record_walk(
                walk_config,
                building,
                (rng_walk, rng_odometry, rng_tags, rng_outliers, rng_poi),
                world_T_upload=world_T_building,
            )
        )
        frames.append(world_T_building)
    return SimulatedBuilding(
        building=building,
        sessions=tuple(sessions),
        world_T_building=tuple(frames),
        styles=tuple(styles[k] if k < len(styles) else WalkStyle() for k in range(count)),
    )


def _walk_seed(building_seed: int, k: int) -> int:
    return int(np.random.SeedSequence([building_seed, k + 1]).generate_state(1)[0])


# ------------------------------------------------------- hooks, alcoves, oblique visits (issue 39)


@dataclass(frozen=True, slots=True, kw_only=True)
class NookConfig:
    """Where real floors break turn-by-turn and a grid of corridors does not (issue 39): corridor
    ends that hook round a corner to their last tag, tags in alcoves off the corridor, and walks
    that go obliquely toward a tag and come back to the corridor's line. Switch each off with 0.

        NookConfig()                                   # the defaults below
        NookConfig(hooks=0, alcoves=0)                 # only the oblique visits
        NO_NOOKS                                       # nothing: the grid as it was

    hooks                   corridor ends (grid nodes on the building's outside, not the start or
                            the stairs) continued outward ``hook_straight_m`` and then round a
                            90° corner (left or right) ``hook_leg_m`` to a tag on the end wall.
    hook_straight_m         (min, max) of the straight part, m.
    hook_leg_m              (min, max) of the part after the corner, to where the walker stands
                            before the end wall's tag, m.
    alcoves                 alcoves off a corridor's wall (one per corridor at most, away from its
                            junctions and its wall's tags), each with a tag on its back wall.
    alcove_depth_m          (min, max) of the back wall's distance from the corridor's wall, m
                            (floor 2's alcove tags hang 2–4 m off the corridor).
    alcove_width_m          the alcove's width, m.
    end_standoff_m          a walker stands this far from the tag at a hook's or alcove's end, m.
    oblique_visit_probability  chance that a walker, passing a tag for the first time, goes to it
                            obliquely (from ``oblique_visit_reach_m`` before it, straight to
                            ``oblique_visit_standoff_m`` from its wall) and back to the
                            corridor's line as far after it, instead of stepping out and back.
    oblique_visit_reach_m   (min, max) of how far before and after the tag the visit leaves and
                            rejoins its line, m.
    oblique_visit_standoff_m  how far from the wall the visit turns back, m.
    """

    hooks: int = 2
    hook_straight_m: tuple[float, float] = (3.0, 6.0)
    hook_leg_m: tuple[float, float] = (3.0, 5.0)
    alcoves: int = 3
    alcove_depth_m: tuple[float, float] = (2.0, 4.0)
    alcove_width_m: float = 1.6
    end_standoff_m: float = 0.6
    oblique_visit_probability: float = 0.6
    oblique_visit_reach_m: tuple[float, float] = (2.0, 4.0)
    oblique_visit_standoff_m: float = 0.4

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            values = value if isinstance(value, tuple) else (value,)
            if not all(math.isfinite(v) and v >= 0 for v in values):
                raise ParameterError(f"{f.name} must be finite and ≥ 0, got {value!r}")
            if isinstance(value, tuple) and value[0] > value[1]:
                raise ParameterError(f"{f.name} must be (min, max), got {value!r}")
        if self.oblique_visit_probability > 1:
            raise ParameterError("oblique_visit_probability must be in [0, 1]")


#: No hooks, alcoves or oblique visits: the building and walks as before issue 39.
NO_NOOKS = NookConfig(hooks=0, alcoves=0, oblique_visit_probability=0.0)


def with_nooks(building: Building, nooks: NookConfig, rng: np.random.Generator) -> Building:
    """``building`` with ``nooks.hooks`` hooked corridor ends and ``nooks.alcoves`` alcoves added
    (new nodes, edges, free-space boxes and one tag at the end of each, numbered after the
    building's tags). A hook is two edges (straight, then round the corner), an alcove one edge
    from a node splitting its corridor. Deterministic for a given ``rng`` state."""
    if nooks.hooks == 0 and nooks.alcoves == 0:
        return building
    nodes = [np.asarray(p, dtype=np.float64) for p in building.node_xyz_m]
    edges = [(int(a), int(b)) for a, b in building.edge_nodes]
    polylines = list(building.edge_polylines_m)
    boxes = [np.asarray(b, dtype=np.float64) for b in building.free_space_boxes_m]
    world_T_tag = dict(building.world_T_tag)
    corridor_tags = list(building.corridor_tag_ids)
    offset_along = dict(building.tag_offset_along_m)
    ends = building.edge_nodes
    xyz = building.node_xyz_m
    is_stairs = np.abs(xyz[ends[:, 0], 1] - xyz[ends[:, 1], 1]) > 1e-9
    stair_nodes = {int(v) for v in ends[is_stairs].ravel()}
    half_w = _corridor_half_width(building)
    low, high = xyz[:, [0, 2]].min(axis=0), xyz[:, [0, 2]].max(axis=0)

    def add_node(p: FloatArray) -> int:
        nodes.append(np.asarray(p, dtype=np.float64))
        return len(nodes) - 1

    def add_tag(at: FloatArray, normal: FloatArray, along_m: float) -> None:
        tag_id = max(world_T_tag) + 1 if world_T_tag else 0
        world_T_tag[tag_id] = _tag_pose(at, normal)
        corridor_tags.append((tag_id,))
        offset_along[tag_id] = along_m

    # hooks: outward from a node on the building's outside
    candidates: list[tuple[int, FloatArray]] = []
    for n in range(len(xyz)):
        if n == 0 or n in stair_nodes:
            continue
        for axis, sign, bound in ((0, -1.0, low[0]), (0, 1.0, high[0]), (1, -1.0, low[1]),
                                  (1, 1.0, high[1])):  # fmt: skip
            if abs(xyz[n, [0, 2][axis]] - bound) < 1e-9:
                out = np.zeros(3)
                out[[0, 2][axis]] = sign
                candidates.append((n, out))
    count = min(nooks.hooks, len(candidates))
    chosen: list[int] = (
        [int(c) for c in rng.choice(len(candidates), size=count, replace=False)] if count else []
    )
    used: set[int] = set()
    for k in sorted(chosen):
        n, out = candidates[k]
        if n in used:
            continue
        used.add(n)
        start = xyz[n]
        straight_m = float(rng.uniform(*nooks.hook_straight_m))
        leg_m = float(rng.uniform(*nooks.hook_leg_m))
        corner = start + straight_m * out
        leg = np.cross(np.array([0.0, 1.0, 0.0]), out) * (1.0 if rng.random() < 0.5 else -1.0)
        end = corner + leg_m * leg
        top = start[1] + _CEILING_M
        straight_box = _box(start + (half_w + 0.6) * out, corner + half_w * out, half_w, top)
        leg_box = _box(corner, end + nooks.end_standoff_m * leg, half_w, top)
        if _overlaps(straight_box, boxes) or _overlaps(leg_box, boxes):
            continue  # into another hook, or round the building's corner into a corridor
        c, e = add_node(corner), add_node(end)
        edges += [(n, c), (c, e)]
        polylines += [np.array([start, corner]), np.array([corner, end])]
        boxes += [_box(start, corner + half_w * out, half_w, top), leg_box]
        tag_height_m = float(rng.uniform(1.2, 1.6))
        add_tag(
            end + nooks.end_standoff_m * leg + np.array([0.0, tag_height_m, 0.0]),
            -leg,
            straight_m + leg_m + nooks.end_standoff_m,
        )

    # alcoves: off the wall of a level corridor, away from its ends and its wall's tags
    tag_xyz = np.array([T[:3, 3] for T in world_T_tag.values()]).reshape(-1, 3)
    corridor_edges = [
        e
        for e in range(len(building.edge_nodes))
        if not is_stairs[e] and len(building.edge_polylines_m[e]) == 2
    ]
    order = rng.permutation(len(corridor_edges))
    made = 0
    for k in order.tolist():
        if made >= nooks.alcoves:
            break
        e = corridor_edges[k]
        a, b = edges[e]
        pa, pb = nodes[a], nodes[b]
        length_m = float(np.linalg.norm(pb - pa))
        forward = (pb - pa) / length_m
        margin_m = half_w + nooks.alcove_width_m + 1.0
        if length_m < 2 * margin_m + 1.0:
            continue
        side = 1.0 if rng.random() < 0.5 else -1.0
        lateral = side * np.cross(np.array([0.0, 1.0, 0.0]), forward)
        along_m = float(rng.uniform(margin_m, length_m - margin_m))
        rel = tag_xyz - pa
        on_wall = (np.abs(rel @ lateral - half_w) < 0.3) & (np.abs(rel[:, 1]) < _CEILING_M)
        if np.any(on_wall & (np.abs(rel @ forward - along_m) < nooks.alcove_width_m / 2 + 0.5)):
            continue
        depth_m = float(rng.uniform(*nooks.alcove_depth_m))
        mouth = pa + along_m * forward
        back = mouth + (half_w + depth_m) * lateral
        stand = back - nooks.end_standoff_m * lateral
        beyond_wall = _box(
            mouth + (half_w + 0.6) * lateral, back, nooks.alcove_width_m / 2, mouth[1] + _CEILING_M
        )
        if _overlaps(beyond_wall, boxes):
            continue  # into a hook, another corridor or the stairwell
        m, s = add_node(mouth), add_node(stand)
        edges[e] = (a, m)
        polylines[e] = np.array([pa, mouth])
        edges += [(m, b), (m, s)]
        polylines += [np.array([mouth, pb]), np.array([mouth, stand])]
        boxes.append(
            _box(mouth + half_w * lateral, back, nooks.alcove_width_m / 2, mouth[1] + _CEILING_M)
        )
        tag_height_m = float(rng.uniform(1.2, 1.6))
        add_tag(back + np.array([0.0, tag_height_m, 0.0]), -lateral, half_w + depth_m)
        tag_xyz = np.vstack([tag_xyz, back])
        made += 1

    return dataclasses.replace(
        building,
        node_xyz_m=np.array(nodes, dtype=np.float64),
        edge_nodes=np.array(edges, dtype=np.int64),
        edge_polylines_m=tuple(polylines),
        free_space_boxes_m=np.array(boxes, dtype=np.float64),
        world_T_tag=world_T_tag,
        corridor_tag_ids=tuple(corridor_tags),
        tag_offset_along_m=offset_along,
    )


#: Free height above a corridor's floor of the boxes added for hooks and alcoves, m.
_CEILING_M = 2.8


def _corridor_half_width(building: Building) -> float:
    """Half the width of the building's first corridor box, m."""
    box = building.free_space_boxes_m[0]
    return float(min(box[1, 0] - box[0, 0], box[1, 2] - box[0, 2]) / 2)


def _box(a: FloatArray, b: FloatArray, half_width_m: float, top_m: float) -> FloatArray:
    """(2, 3) the axis-aligned free-space box of a straight corridor from ``a`` to ``b`` (floor
    level, along x or z), ``half_width_m`` to each side of its line."""
    grow = np.array([half_width_m, 0.0, half_width_m])
    lo, hi = np.minimum(a, b) - grow, np.maximum(a, b) + grow
    along = np.abs(b - a)[[0, 2]].argmax()
    axis = [0, 2][int(along)]
    lo[axis], hi[axis] = min(a[axis], b[axis]), max(a[axis], b[axis])
    lo[1], hi[1] = min(a[1], b[1]), top_m
    return np.array([lo, hi])


def _overlaps(box: FloatArray, boxes: Sequence[FloatArray], *, margin_m: float = 0.5) -> bool:
    """Whether ``box`` (2, 3), grown by ``margin_m`` horizontally, meets any of ``boxes``
    (each (2, 3)) on its floor."""
    grow = np.array([margin_m, 0.0, margin_m])
    lo, hi = box[0] - grow, box[1] + grow
    return any(
        bool(np.all(lo <= other[1]) and np.all(other[0] <= hi) and lo[1] < other[1][1])
        for other in boxes
        if other[0][1] <= box[0][1] + 0.5 and box[0][1] < other[1][1]
    )


def _tag_pose(at: FloatArray, normal: FloatArray) -> FloatArray:
    """(4, 4) a wall tag's pose at ``at``: +z along ``normal`` (horizontal), +y up."""
    up = np.array([0.0, 1.0, 0.0])
    world_T = np.eye(4)
    world_T[:3, 0] = np.cross(up, normal)
    world_T[:3, 1] = up
    world_T[:3, 2] = normal
    world_T[:3, 3] = at
    return world_T


def with_oblique_visits(
    walk: SimulatedWalk, nooks: NookConfig, rng: np.random.Generator
) -> SimulatedWalk:
    """``walk`` with its first pass by each tag (with ``nooks.oblique_visit_probability``) bent
    into an oblique visit: straight from the position ``reach`` before the tag to
    ``oblique_visit_standoff_m`` in front of it, and straight back to the position ``reach``
    after it (``reach`` drawn from ``oblique_visit_reach_m``), as real mappers veer to a tag and
    drift back to the corridor's line. Only where that stretch of the walk is straight (the ends
    of the stretch within 20° of its line) and level."""
    if nooks.oblique_visit_probability == 0:
        return walk
    positions = walk.positions_m.copy()
    spacing_m = float(np.median(np.linalg.norm(np.diff(positions, axis=0), axis=1)))
    for tag in walk.tag_ids:
        world_T_tag = walk.building.world_T_tag[tag]
        target = world_T_tag[:3, 3] + nooks.oblique_visit_standoff_m * world_T_tag[:3, 2]
        horizontal_m = np.hypot(*(positions[:, [0, 2]] - target[[0, 2]]).T)
        same_floor = np.abs(positions[:, 1] - target[1]) < 1.5
        near = np.flatnonzero(same_floor & (horizontal_m < 2.5))
        reach_m = float(rng.uniform(*nooks.oblique_visit_reach_m))
        if near.size == 0 or rng.uniform() >= nooks.oblique_visit_probability:
            continue
        first_pass = near[near < near[0] + int(5.0 / spacing_m)]
        k = int(first_pass[np.argmin(horizontal_m[first_pass])])
        span = max(2, round(reach_m / spacing_m))
        i, j = k - span, k + span
        if i < 0 or j >= len(positions):
            continue
        stretch = positions[i : j + 1]
        chord = stretch[-1] - stretch[0]
        chord_m = float(np.hypot(chord[0], chord[2]))
        if chord_m < 1.5 * reach_m or np.ptp(stretch[:, 1]) > 0.05:
            continue  # not a straight level stretch: a corner, a turn-back or the stairs
        off_line_m = np.abs(np.cross(chord[[0, 2]], (stretch - stretch[0])[:, [0, 2]])) / chord_m
        if (
            float(off_line_m.max()) > 1.0
            or float(np.hypot(*(stretch[span] - target)[[0, 2]])) > 2.5
        ):
            continue
        goal = np.array([target[0], positions[k, 1], target[2]])
        t = np.linspace(0.0, 1.0, span + 1)[:, None]
        positions[i : k + 1] = positions[i] + t * (goal - positions[i])
        positions[k : j + 1] = goal + t * (positions[j] - goal)
    return dataclasses.replace(walk, positions_m=positions)


def nook_walks(
    config: SimulationConfig,
    seed: int,
    walkers: Sequence[WalkerConfig],
    nooks: NookConfig,
    *,
    length_m: float = 600.0,
) -> list[SimulatedWalk]:
    """The walks of ``walkers`` through one building of ``config`` (seed ``seed``) with ``nooks``
    (:func:`with_nooks`), in the building's frame; walker k walks with seed ``100 × seed + k``
    and makes oblique visits as ``nooks`` says. With :data:`NO_NOOKS` these are
    ``simulate.walks_of_one_building``'s walks."""
    rng = np.random.default_rng(seed)
    building = build_building(dataclasses.replace(config, seed=seed), rng)
    building = with_nooks(building, nooks, np.random.default_rng([seed, 39]))
    walks = []
    for k, walker in enumerate(walkers):
        w = simulate_walk(
            config,
            dataclasses.replace(walker, seed=100 * seed + k, length_m=length_m),
            building=building,
        )
        walks.append(with_oblique_visits(w, nooks, np.random.default_rng([seed, k, 39])))
    return walks
