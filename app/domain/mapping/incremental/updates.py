"""Build, add a walk, remove a walk: the building map kept as summaries (issue 38).

    state, served = build([Walk(walk_id="w1", session=s1), ...], params)
    state, served = add_walk(state, Walk(walk_id="w9", session=s9), params, load=load_session_by_id)
    state, served = remove_walk(state, "w3", params, load=load_session_by_id)

Each change: the new walk (if any) screened, depth-scaled and optimized alone with its noise
estimated from its own residuals (``joint.plan_sessions`` of that walk alone: the batch build's
step 1, the same :class:`WalkFit`), placed on the building's tags (``joint.align_session``) and
condensed to its summary where the building holds the tags it shares (its poses fitted to them);
then the building (tags and placements) solved under all summaries, and every walk whose tags
moved further than ``RELINEARIZE_M`` / ``RELINEARIZE_RAD`` from where its summary was made is
linearized again there (its poses fitted to the building's tags, its summary made anew:
``load(walk_id)`` gives its session), new walks first, and the building solved again, until none
moved that far. A walk not relinearized keeps its poses, moved rigidly with its placement: they
are off the batch map's by about the tolerance (1 cm), its tags' share of the map by far less
(0.1 mm on the tests' buildings).

A summary is a Gauss–Newton model of its walk: exact in its gradient where it was made, not in
its curvature once the walk is bent far from its own optimum (a walk alone drifts by decimetres
to a metre from the building), so a walk the building moved by centimetres must be relinearized
(measured: 4 cm unrelinearized offsets gave tags 9 mm off the batch map). Adding a walk to a
small building moves the others by centimetres (12 walks: 11 relinearized; 100: 4).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from app.domain.errors import InvisibleMapError
from app.domain.frames import FloatArray, make_pose, se3_inverse
from app.domain.mapping.joint import (
    MIN_SHARED_TAGS,
    AlignmentError,
    JointMap,
    WalkFit,
    align_session,
    plan_sessions,
    scaled_tag_depths,
)
from app.domain.mapping.params import SlamParams
from app.domain.mapping.screening import screen_detections
from app.domain.upload.session import Session

from .building import offset_size, solve_building
from .state import BuildingState, IntArray, StaleStateError, Walk, WalkSummary, walk_fingerprint
from .summary import summarize_walk

#: A walk's summary is made again where the building moved one of its tags (in its own frame)
#: further than this from where it was made, m and rad. Its served poses are off by about as much
#: until it is (tests: 1 cm tags, 5 cm poses from the batch build).
RELINEARIZE_M = 0.01
RELINEARIZE_RAD = 0.005
#: Rounds at most in which only the new walks are relinearized (until they settle).
FRESH_ROUNDS = 3
#: Most rounds of solving the building and relinearizing the walks that moved. A building that
#: has not settled by then is served as it is (``IncrementalMap.round_log`` shows it): the outer
#: loop has no check of the walks' true cost, and a walk pulled metres from its own optimum
#: (desnat_straight_once, whose odometry runs 3% long) swings instead of settling.
MAX_ROUNDS = 6

#: Gives a walk's session by its id (the walks already in the building, to relinearize them).
SessionLoader = Callable[[str], Session]


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class IncrementalMap:
    """What a building map serves: its tags and every walk's poses, in the map frame (the first
    walk's world), and what the change cost.

    walk_ids: in the map's order. tag_ids: (T,) sorted; map_T_tag: (T, 4, 4), m.
    world_T_phone: per walk, (N_s, 4, 4) its poses in the map frame.
    relinearized: the walks whose summaries this change made again (a new walk counts).
    rounds, iterations: building solves and their iterations in all.
    timings_ms: CPU time by step (``time.process_time``).
    round_log: per building solve, how many walks it sent to be relinearized and the largest
        offset of a walk's tag from its summary's linearization point (m, rad).
    """

    walk_ids: tuple[str, ...]
    tag_ids: IntArray
    map_T_tag: FloatArray
    world_T_phone: tuple[FloatArray, ...]
    relinearized: tuple[str, ...] = ()
    rounds: int = 0
    iterations: int = 0
    timings_ms: dict[str, float] = field(default_factory=dict)
    round_log: tuple[tuple[int, float, float], ...] = ()

    def tag_poses(self) -> dict[int, FloatArray]:
        return {int(t): pose for t, pose in zip(self.tag_ids, self.map_T_tag, strict=True)}

    def walk_poses(self, walk_id: str) -> FloatArray:
        return self.world_T_phone[self.walk_ids.index(walk_id)]

    def largest_differences_m(self, joint: JointMap) -> tuple[float, float]:
        """The largest tag and pose position differences to ``joint``, the batch map of the
        same walks (both in the first walk's world), m. ValueError when ``joint`` has other
        walks or other tags."""
        if self.walk_ids != tuple(part.dataset for part in joint.parts):
            raise ValueError(f"other walks: {self.walk_ids} against the batch map's")
        batch_tags, served_tags = joint.map.tag_poses(), self.tag_poses()
        if set(batch_tags) != set(served_tags):
            raise ValueError(f"other tags: {sorted(set(batch_tags) ^ set(served_tags))}")
        tag_m = max(
            float(np.linalg.norm(batch_tags[t][:3, 3] - served_tags[t][:3, 3])) for t in batch_tags
        )
        pose_m = max(
            float(
                np.max(
                    np.linalg.norm(
                        joint.map.world_T_phone[part.pose_rows, :3, 3]
                        - self.walk_poses(part.dataset)[:, :3, 3],
                        axis=1,
                    )
                )
            )
            for part in joint.parts
        )
        return tag_m, pose_m


def build(
    walks: Sequence[Walk],
    params: SlamParams | None = None,
    *,
    tolerance: tuple[float, float] = (RELINEARIZE_M, RELINEARIZE_RAD),
    fits: Sequence[WalkFit] = (),
) -> tuple[BuildingState, IncrementalMap]:
    """The building map of ``walks`` from scratch (the first walk's world is the map frame): each
    walk optimized alone and placed as the batch build does (``joint.plan_sessions``; ``fits``:
    walks optimized alone before, reused as it reuses them), then summarized and solved as a
    building. Raises ``AlignmentError`` for a walk that cannot be placed."""
    params = params or SlamParams()
    clock = Clock()
    if not walks:
        raise InvisibleMapError("a map needs at least one session")
    plan = plan_sessions(
        [w.session for w in walks], params, names=[w.walk_id for w in walks], fits=fits
    )
    clock.lap("walks_alone")
    summaries = []
    for walk, session, screening, fit in zip(
        walks, plan.sessions, plan.screenings, plan.fits, strict=True
    ):
        summaries.append(
            summarize_walk(
                walk_id=walk.walk_id,
                fingerprint=walk_fingerprint(walk.session),
                session=session,
                screening=screening,
                params=params,
                noise_scales=fit.noise_scales,
                depth_scale=fit.tag_depth_scale,
                world_T_phone=fit.alone.world_T_phone,
                world_T_tag=fit.alone.tag_poses(),
                hold_tags=False,
            )
        )
    clock.lap("summaries")
    placements = np.stack([a.map_T_world for a in plan.alignments])
    tag_ids, map_T_tag = _placed_tags(summaries, placements)
    state = BuildingState(
        walks=tuple(summaries),
        map_T_world=placements,
        tag_ids=tag_ids,
        map_T_tag=map_T_tag,
        params=params.to_dict(),
    )
    sessions = {w.walk_id: w.session for w in walks}
    return _settle(
        state, params, sessions.__getitem__, clock, new=set(sessions), tolerance=tolerance
    )


def add_walk(
    state: BuildingState,
    walk: Walk,
    params: SlamParams | None = None,
    *,
    load: SessionLoader | None = None,
    tolerance: tuple[float, float] = (RELINEARIZE_M, RELINEARIZE_RAD),
    fit: WalkFit | None = None,
) -> tuple[BuildingState, IncrementalMap]:
    """``state`` with ``walk`` added (last in the map's order). ``load``: the sessions of the
    walks already in the building, by id, for those the new walk moves enough to relinearize
    (without it they are moved rigidly only). ``fit``: the walk optimized alone already (reused
    when its parameters are these). Raises :class:`StaleStateError` when ``params``
    are not the state's, ``AlignmentError`` when no tags place the walk."""
    params = params or SlamParams()
    _require_params(state, params)
    if walk.walk_id in state.walk_ids:
        raise InvisibleMapError(f"walk {walk.walk_id!r} is in the building already")
    clock = Clock()
    plan = plan_sessions(
        [walk.session], params, names=[walk.walk_id], fits=[fit] if fit is not None else ()
    )
    fit = plan.fits[0]
    clock.lap("walks_alone")
    map_tags = {int(t): pose for t, pose in zip(state.tag_ids, state.map_T_tag, strict=True)}
    alignment = align_session(
        walk.walk_id, fit.alone.tag_poses(), map_tags, min_shared_tags=MIN_SHARED_TAGS
    )
    clock.lap("placing")
    # linearized where the building holds the tags it shares (its own optimum is decimetres and
    # degrees off there: a summary made at it would need relinearizing at once)
    world_T_map = se3_inverse(alignment.map_T_world)
    world_T_tag = {
        t: world_T_map @ map_tags[t] if t in map_tags else pose
        for t, pose in fit.alone.tag_poses().items()
    }
    summary = summarize_walk(
        walk_id=walk.walk_id,
        fingerprint=walk_fingerprint(walk.session),
        session=plan.sessions[0],
        screening=plan.screenings[0],
        params=params,
        noise_scales=fit.noise_scales,
        depth_scale=fit.tag_depth_scale,
        world_T_phone=fit.alone.world_T_phone,
        world_T_tag=world_T_tag,
        hold_tags=True,
        cost_alone=fit.cost,
    )
    clock.lap("summaries")
    walks = (*state.walks, summary)
    placements = np.concatenate([state.map_T_world, alignment.map_T_world[None]])
    new_ids, new_tags = _placed_tags([summary], alignment.map_T_world[None])
    merged = dict(zip(new_ids.tolist(), new_tags, strict=True)) | map_tags
    tag_ids = np.array(sorted(merged), dtype=np.int64)
    grown = BuildingState(
        walks=walks,
        map_T_world=placements,
        tag_ids=tag_ids,
        map_T_tag=np.stack([merged[int(t)] for t in tag_ids]),
        params=state.params,
    )

    def loader(walk_id: str) -> Session:
        if walk_id == walk.walk_id:
            return walk.session
        if load is None:
            raise KeyError(walk_id)
        return load(walk_id)

    return _settle(
        grown,
        params,
        loader,
        clock,
        new={walk.walk_id},
        optional=load is None,
        tolerance=tolerance,
    )


def remove_walk(
    state: BuildingState,
    walk_id: str,
    params: SlamParams | None = None,
    *,
    load: SessionLoader | None = None,
    tolerance: tuple[float, float] = (RELINEARIZE_M, RELINEARIZE_RAD),
) -> tuple[BuildingState, IncrementalMap]:
    """``state`` without walk ``walk_id``: its summary dropped, the tags only it saw with it; if
    it was the first walk, the next one's world becomes the map frame. Raises ``AlignmentError``
    when a walk is left that no other walk's tags place."""
    params = params or SlamParams()
    _require_params(state, params)
    if walk_id not in state.walk_ids:
        raise InvisibleMapError(f"walk {walk_id!r} is not in the building")
    if len(state.walks) == 1:
        raise InvisibleMapError("a map needs at least one session: delete the map instead")
    clock = Clock()
    keep = [s for s, w in enumerate(state.walks) if w.walk_id != walk_id]
    walks = tuple(state.walks[s] for s in keep)
    first_T_map = se3_inverse(state.map_T_world[keep[0]])
    placements = first_T_map @ state.map_T_world[keep]
    placements[0] = np.eye(4)
    seen = {int(t) for w in walks for t in w.tag_ids}
    rows = [k for k, t in enumerate(state.tag_ids.tolist()) if t in seen]
    _require_placed(walks)
    shrunk = BuildingState(
        walks=walks,
        map_T_world=placements,
        tag_ids=state.tag_ids[rows],
        map_T_tag=first_T_map @ state.map_T_tag[rows],
        params=state.params,
    )
    clock.lap("placing")

    def loader(walk: str) -> Session:
        if load is None:
            raise KeyError(walk)
        return load(walk)

    return _settle(
        shrunk, params, loader, clock, new=set(), optional=load is None, tolerance=tolerance
    )


def _settle(
    state: BuildingState,
    params: SlamParams,
    load: SessionLoader,
    clock: Clock,
    *,
    new: set[str],
    optional: bool = False,
    tolerance: tuple[float, float] = (RELINEARIZE_M, RELINEARIZE_RAD),
) -> tuple[BuildingState, IncrementalMap]:
    """Solve the building, relinearize the walks whose tags moved, until none did."""
    walks = list(state.walks)
    placements, map_T_tag = state.map_T_world, state.map_T_tag
    relinearized: list[str] = []
    log: list[tuple[int, float, float]] = []
    rounds = iterations = 0
    while True:
        rounds += 1
        solution = solve_building(walks, placements, state.tag_ids, map_T_tag)
        iterations += solution.iterations
        placements, map_T_tag = solution.map_T_world, solution.map_T_tag
        clock.lap("building")
        moved = [
            s
            for s, delta in enumerate(solution.offsets)
            if _beyond(offset_size(delta), tolerance) and (not optional or walks[s].walk_id in new)
        ]
        # a new walk's summary, made at its own optimum, is off where the building pulls it:
        # settle the new walks first, then see which old walks their pull really moved
        fresh = [s for s in moved if walks[s].walk_id in new]
        if fresh and rounds < FRESH_ROUNDS:
            moved = fresh
        largest = max((offset_size(d) for d in solution.offsets), default=(0.0, 0.0))
        log.append((len(moved), largest[0], largest[1]))
        if not moved or rounds >= MAX_ROUNDS:
            break
        for s in moved:
            walks[s] = _relinearized(
                walks[s], placements[s], state.tag_ids, map_T_tag, load, params
            )
            if walks[s].walk_id not in relinearized:
                relinearized.append(walks[s].walk_id)
        clock.lap("relinearize")
    settled = BuildingState(
        walks=tuple(walks),
        map_T_world=placements,
        tag_ids=state.tag_ids,
        map_T_tag=map_T_tag,
        params=state.params,
    )
    served = IncrementalMap(
        walk_ids=settled.walk_ids,
        tag_ids=settled.tag_ids,
        map_T_tag=map_T_tag,
        world_T_phone=tuple(
            map_T_world @ w.world_T_phone for w, map_T_world in zip(walks, placements, strict=True)
        ),
        relinearized=tuple(w for w in settled.walk_ids if w in set(relinearized) | new),
        rounds=rounds,
        iterations=iterations,
        timings_ms=clock.laps,
        round_log=tuple(log),
    )
    return settled, served


def _relinearized(
    walk: WalkSummary,
    map_T_world: FloatArray,
    tag_ids: IntArray,
    map_T_tag: FloatArray,
    load: SessionLoader,
    params: SlamParams,
) -> WalkSummary:
    """``walk``'s summary made again where the building puts its tags (its poses fitted to them)."""
    session = load(walk.walk_id)
    if walk_fingerprint(session) != walk.fingerprint:
        raise StaleStateError(
            f"walk {walk.walk_id!r}'s data are not those its summary was made from"
        )
    index = {int(t): k for k, t in enumerate(tag_ids.tolist())}
    world_T_map = se3_inverse(map_T_world)
    world_T_tag = {int(t): world_T_map @ map_T_tag[index[int(t)]] for t in walk.tag_ids}
    return summarize_walk(
        walk_id=walk.walk_id,
        fingerprint=walk.fingerprint,
        session=scaled_tag_depths(session, walk.depth_scale),
        screening=screen_detections(session.detections, params),
        params=params,
        noise_scales=walk.noise_scales,
        depth_scale=walk.depth_scale,
        world_T_phone=walk.world_T_phone,
        world_T_tag=world_T_tag,
        hold_tags=True,
        cost_alone=walk.cost_alone,
        relinearized=walk.relinearized + 1,
    )


def _beyond(size: tuple[float, float], tolerance: tuple[float, float]) -> bool:
    return size[0] > tolerance[0] or size[1] > tolerance[1]


def _placed_tags(
    walks: Sequence[WalkSummary], placements: FloatArray
) -> tuple[IntArray, FloatArray]:
    """Each tag where the walks put it: the mean position, the first walk's rotation."""
    positions: dict[int, list[FloatArray]] = {}
    rotations: dict[int, FloatArray] = {}
    for walk, map_T_world in zip(walks, placements, strict=True):
        for t, pose in zip(walk.tag_ids.tolist(), map_T_world @ walk.world_T_tag, strict=True):
            positions.setdefault(t, []).append(pose[:3, 3])
            rotations.setdefault(t, pose[:3, :3])
    tag_ids = np.array(sorted(positions), dtype=np.int64)
    poses = np.stack(
        [make_pose(rotations[t], np.mean(positions[t], axis=0)) for t in tag_ids.tolist()]
    )
    return tag_ids, poses


def _require_params(state: BuildingState, params: SlamParams) -> None:
    if SlamParams.from_dict(state.params) != params:
        raise StaleStateError("the state was made with other parameters: build from scratch")


def _require_placed(walks: Sequence[WalkSummary]) -> None:
    """Every walk shares at least ``MIN_SHARED_TAGS`` tags with the others, and the walks form
    one group through such tags."""
    if len(walks) < 2:
        return
    tags = [set(w.tag_ids.tolist()) for w in walks]
    reached, frontier = {0}, [0]
    while frontier:
        s = frontier.pop()
        for o in range(len(walks)):
            if o not in reached and len(tags[s] & tags[o]) >= MIN_SHARED_TAGS:
                reached.add(o)
                frontier.append(o)
    for s in range(len(walks)):
        if s not in reached:
            others = set().union(*(tags[o] for o in range(len(walks)) if o != s))
            shared = tags[s] & others
            raise AlignmentError(
                walks[s].walk_id,
                "no_shared_tags" if not shared else "too_few_shared_tags",
                f"without the walk removed it shares tags {sorted(shared)} with the others",
            )


class Clock:
    """CPU time by step, ms."""

    def __init__(self) -> None:
        self.laps: dict[str, float] = {}
        self._last = time.process_time()
        self._start = self._last

    def lap(self, step: str) -> None:
        now = time.process_time()
        self.laps[step] = self.laps.get(step, 0.0) + (now - self._last) * 1e3
        self.laps["total"] = (now - self._start) * 1e3
        self._last = now


__all__ = ["IncrementalMap", "SessionLoader", "add_walk", "build", "remove_walk"]
