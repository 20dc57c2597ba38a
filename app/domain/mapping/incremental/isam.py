"""A building map in gtsam's ISAM2: a walk added or removed at about what that walk costs.

    building, served = IsamBuilding.build(walks, params)     # from scratch
    served = building.add(Walk(walk_id="w9", session=s9))    # its factors into the tree
    served = building.remove("w3")                           # its factors out of it
    state = building.state()                                 # as data (isam_state.py)
    building, served = IsamBuilding.restore(state, walks, params)   # a restarted worker

The graph is the batch build's joint graph (``joint.optimize_sessions``, step 4), walk by walk:
each walk screened, its tag depths scaled and its noise estimated from its own data as the batch
build does it (``joint.plan_sessions``: the same ``WalkFit``), its odometry, gravity and tag
factors exactly those of its chain in the joint graph (``slam.chain_graph``; tested factor for
factor), its poses keyed from a key offset of its own, so that the tree knows each walk's
factors by their indices. The first walk's first pose holds the gauge.

- *add*: the new walk optimized alone (``plan_sessions`` of it), placed on the map's tags
  (``joint.align_session``), its factors and variables given to ``ISAM2.update``;
- *remove*: its factors taken out (``removeFactorIndices``). ISAM2 drops the variables no factor
  is left on (the walk's poses, the tags only it saw): nothing is left unconstrained, so no prior
  or marginalization is needed, and the map is that of never having added it. Removing the
  first walk takes the gauge with it: the next walk's first pose gets the gauge prior where the
  tree holds it, and the map is drawn in that walk's world (a turn about +y and a translation,
  ``map_T_graph``), as the batch build of the walks left draws it;
- after either, ``ISAM2.update()`` until it relinearizes nothing (every variable's step below
  ``RELINEARIZE_THRESHOLD``): the optimum of the graph, as the batch build's LM finds it, to
  within millimetres (a first build also makes the tree anew once at its settled estimate).

What it serves is the batch build's map where the batch build keeps every walk as it is. What
it does not redo (``bench/incremental.py`` measures where the batch build did): step 3 (a walk's
odometry rescaled), step 5 (a tag one walk disagrees on set apart) and step 6 (a walk
down-weighted for its disagreement). Each is a change of one walk's factors, which the tree can
take out and put in again; deciding them needs the walks' costs at the optimum, not done here.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X

from app.domain.errors import InvisibleMapError
from app.domain.frames import FloatArray, make_pose, se3_inverse
from app.domain.mapping.joint import (
    MIN_SHARED_TAGS,
    AlignmentError,
    WalkFit,
    align_session,
    plan_sessions,
    scaled_tag_depths,
    yaw_of,
)
from app.domain.mapping.keyframes import interpolate_poses
from app.domain.mapping.params import SlamParams
from app.domain.mapping.screening import Screening, screen_detections
from app.domain.mapping.slam import GraphInputs, chain_graph, gauge_prior, to_pose3
from app.domain.upload.session import Session

from .isam_state import IsamState, IsamWalkState
from .state import IntArray, StaleStateError, Walk, walk_fingerprint
from .updates import Clock, IncrementalMap

#: ISAM2 linearizes a variable again when its step is larger than this (its tangent vector,
#: rad and m): the served map is one Gauss–Newton step from where each variable was linearized.
#: Against the batch build (bench/incremental.py): 0.3 mm at 20 walks; 7.7 mm at 50, one walk
#: along a direction its χ² barely sees (0.13 for those 7.7 mm); 0.01 gave 7.9 mm at 20.
RELINEARIZE_THRESHOLD = 0.003
#: Most ``ISAM2.update`` calls after one change (a change that has not settled by then is served
#: as it is: ``IncrementalMap.rounds`` shows it).
MAX_UPDATES = 20

_POSE_KEY = ord("x") << 56
_TAG_KEY = ord("l") << 56


@dataclass(slots=True, kw_only=True, eq=False)
class WalkInTree:
    """A walk in the tree: what makes its factors, where they are, where its poses are keyed."""

    walk_id: str
    fingerprint: str
    #: its session with its tag depths scaled, in its own world (the graph's measurements)
    session: Session
    depth_scale: float
    noise_scales: FloatArray
    cost_alone: float
    key_offset: int
    keyframes: IntArray
    #: (4, 4) its world placed in the tree's frame (where its odometry starts from)
    graph_T_world: FloatArray
    tag_ids: frozenset[int]
    #: its factors' indices in the tree (a gauge prior it holds among them)
    factor_indices: list[int]
    #: which of its sightings the graph uses (the parameters' screening of its session)
    screening: Screening
    #: its own map's tags alone, in its own world (``IsamWalkState.alone_tag_ids``)
    alone_tags: dict[int, FloatArray]
    #: its fit alone, when this process made it or was given it (a restored walk has none)
    fit: WalkFit | None = None


class IsamBuilding:
    """A building map held in an ``ISAM2`` tree (the module docstring). Not thread-safe; one
    per map in a worker process."""

    def __init__(self, params: SlamParams) -> None:
        self.params = params
        self._fixed = dataclasses.replace(params, estimate_noise=False)
        settings = gtsam.ISAM2Params()
        settings.setRelinearizeThreshold(RELINEARIZE_THRESHOLD)
        settings.relinearizeSkip = 1
        settings.findUnusedFactorSlots = True  # a removed walk's slots serve the next one
        self._isam = gtsam.ISAM2(settings)
        self._walks: list[WalkInTree] = []
        #: the map frame (the first walk's world) from the tree's: the identity until the
        #: walk that held the gauge is removed
        self._map_T_graph = np.eye(4)
        self._next_key = 0

    @property
    def walk_ids(self) -> tuple[str, ...]:
        return tuple(w.walk_id for w in self._walks)

    @property
    def walks(self) -> tuple[WalkInTree, ...]:
        """The walks in the map's order, as the tree holds them (read, do not change)."""
        return tuple(self._walks)

    def map_T_world(self, walk: WalkInTree) -> FloatArray:
        """(4, 4) where ``walk``'s world sits in the map frame."""
        return np.asarray(self._map_T_graph @ walk.graph_T_world, dtype=np.float64)

    # ------------------------------------------------------------------ the three changes

    @classmethod
    def build(
        cls,
        walks: Sequence[Walk],
        params: SlamParams | None = None,
        *,
        fits: Sequence[WalkFit] = (),
    ) -> tuple[IsamBuilding, IncrementalMap]:
        """The building map of ``walks`` from scratch: each walk fitted alone and all placed as
        the batch build does (``plan_sessions``; ``fits``: walks fitted before, reused), LM's
        start of the batch build (each walk's own optimum placed, each tag at the mean of where
        the walks put it) given to ISAM2, updated until it settles. Raises ``AlignmentError``
        for a walk that cannot be placed."""
        params = params or SlamParams()
        if not walks:
            raise InvisibleMapError("a map needs at least one session")
        clock = Clock()
        plan = plan_sessions(
            [w.session for w in walks], params, names=[w.walk_id for w in walks], fits=fits
        )
        clock.lap("walks_alone")
        building = cls(params)
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        counts: list[int] = []
        positions: dict[int, list[FloatArray]] = {}
        rotations: dict[int, FloatArray] = {}
        for s, walk in enumerate(walks):
            fit, alignment = plan.fits[s], plan.alignments[s]
            inputs = building._inputs(plan.sessions[s], plan.screenings[s], fit.noise_scales)
            walk_graph = chain_graph(
                inputs, building._fixed, key_offset=building._next_key, gauge=s == 0
            )
            counts.append(int(walk_graph.size()))
            graph.push_back(walk_graph)
            placed = alignment.place(fit.alone.world_T_phone)
            for i in inputs.keyframes.tolist():
                values.insert(X(building._next_key + i), to_pose3(placed[i]))
            alone = fit.alone.tag_poses()
            for t in inputs.tag_rows:
                pose = alignment.place(alone[t]) if t in alone else _initial(inputs, t)
                positions.setdefault(t, []).append(pose[:3, 3])
                rotations.setdefault(t, pose[:3, :3])
            building._walks.append(
                building._walk(
                    walk, plan.sessions[s], plan.screenings[s], fit, inputs, alignment.map_T_world
                )
            )
            building._next_key += plan.sessions[s].num_poses
        for t, p in positions.items():
            values.insert(L(t), to_pose3(make_pose(rotations[t], np.mean(np.stack(p), axis=0))))
        clock.lap("graph")
        result = building._isam.update(graph, values)
        building._take_indices(building._walks, counts, result)
        updates = building._settle()
        # the variables linearized far from the optimum and not since (their steps below the
        # threshold) leave the estimate millimetres off (50 walks: 12 mm): linearized again at
        # the settled estimate, all at once (one elimination, as ``restore`` makes the tree)
        updates += building._relinearize_all()
        clock.lap("isam")
        return building, building.served(clock, updates)

    def add(self, walk: Walk, *, fit: WalkFit | None = None) -> IncrementalMap:
        """Add ``walk`` (last in the map's order): fitted alone (``fit``: already, reused when
        its parameters are these), placed on the map's tags, its factors into the tree. Raises
        ``AlignmentError`` when no tags place it; the tree is then as it was."""
        if walk.walk_id in self.walk_ids:
            raise InvisibleMapError(f"walk {walk.walk_id!r} is in the building already")
        clock = Clock()
        plan = plan_sessions(
            [walk.session],
            self.params,
            names=[walk.walk_id],
            fits=[fit] if fit is not None else (),
        )
        fit = plan.fits[0]
        clock.lap("walk_alone")
        map_tags = self._map_tags()
        alignment = align_session(
            walk.walk_id, fit.alone.tag_poses(), map_tags, min_shared_tags=MIN_SHARED_TAGS
        )
        graph_T_world = se3_inverse(self._map_T_graph) @ alignment.map_T_world
        clock.lap("placing")
        inputs = self._inputs(plan.sessions[0], plan.screenings[0], fit.noise_scales)
        graph = chain_graph(inputs, self._fixed, key_offset=self._next_key, gauge=False)
        values = gtsam.Values()
        placed = graph_T_world @ fit.alone.world_T_phone[inputs.keyframes]
        for i, pose in zip(inputs.keyframes.tolist(), placed, strict=True):
            values.insert(X(self._next_key + i), to_pose3(pose))
        alone = fit.alone.tag_poses()
        for t in inputs.tag_rows:
            if not self._isam.valueExists(L(t)):
                pose = alone[t] if t in alone else _initial(inputs, t)
                values.insert(L(t), to_pose3(graph_T_world @ pose))
        added = self._walk(walk, plan.sessions[0], plan.screenings[0], fit, inputs, graph_T_world)
        clock.lap("graph")
        result = self._isam.update(graph, values)
        self._walks.append(added)
        self._next_key += plan.sessions[0].num_poses
        self._take_indices([added], [int(graph.size())], result)
        updates = self._settle()
        clock.lap("isam")
        return self.served(clock, updates)

    def remove(self, walk_id: str) -> IncrementalMap:
        """Take walk ``walk_id`` out: its factors removed, with them its poses and the tags only
        it saw. Raises ``AlignmentError`` when a walk would be left that no other walk's tags
        place (the tree is then as it was)."""
        ids = self.walk_ids
        if walk_id not in ids:
            raise InvisibleMapError(f"walk {walk_id!r} is not in the building")
        if len(ids) == 1:
            raise InvisibleMapError("a map needs at least one session: delete the map instead")
        clock = Clock()
        s = ids.index(walk_id)
        gone = self._walks[s]
        left = [w for w in self._walks if w is not gone]
        _require_placed(left)
        new_factors = gtsam.NonlinearFactorGraph()
        if s == 0:  # the gauge goes with it: the next walk's first pose holds it where it is
            first = left[0]
            key = X(first.key_offset)
            graph_T_first = self._isam.calculateEstimatePose3(key).matrix()
            new_factors.add(gauge_prior(key, graph_T_first))
            self._map_T_graph = _turn_and_shift(graph_T_first, first.session.world_T_phone[0])
        result = self._isam.update(new_factors, gtsam.Values(), gone.factor_indices)
        if s == 0:
            left[0].factor_indices.extend(int(k) for k in result.getNewFactorsIndices())
        self._walks = left
        updates = self._settle()
        clock.lap("isam")
        return self.served(clock, updates)

    def odometry_scale_drop(self, walk_id: str, scale: float) -> float | None:
        """How much the map's cost (χ², 2 × gtsam's error) drops when walk ``walk_id``'s
        odometry lengths are multiplied by ``scale``: the batch build's scale test
        (``joint.scale.tested_scales``) made in the tree. The walk's factors are swapped for
        ones made from its scaled odometry, the tree settles, the cost is read, and its own
        factors are swapped back (the tree then settles where it was, to the relinearization
        threshold). None where the tree cannot test it: the walk holding the gauge, whose
        scaling moves the map frame itself, or other keyframes once scaled."""
        ids = self.walk_ids
        s = ids.index(walk_id)
        walk = self._walks[s]
        if s == 0:
            return None
        scaled = dataclasses.replace(
            walk.session, world_T_phone=_scaled_translations(walk.session.world_T_phone, scale)
        )
        scaled_inputs = self._inputs(scaled, walk.screening, walk.noise_scales)
        if not np.array_equal(scaled_inputs.keyframes, walk.keyframes):
            return None
        unscaled = 2.0 * self._cost()
        self._swap_factors(walk, scaled_inputs)
        rescaled = 2.0 * self._cost()
        self._swap_factors(walk, self._inputs(walk.session, walk.screening, walk.noise_scales))
        return unscaled - rescaled

    def _swap_factors(self, walk: WalkInTree, inputs: GraphInputs) -> None:
        """``walk``'s factors in the tree replaced by those of ``inputs`` (its session, scaled
        or not), on the same variables; settled."""
        graph = chain_graph(inputs, self._fixed, key_offset=walk.key_offset, gauge=False)
        result = self._isam.update(graph, gtsam.Values(), walk.factor_indices)
        walk.factor_indices = [int(k) for k in result.getNewFactorsIndices()]
        self._settle()

    def _cost(self) -> float:
        """gtsam's error of the tree's factors at its estimate (removed slots skipped)."""
        return float(self._isam.getFactorsUnsafe().error(self._isam.calculateEstimate()))

    # ------------------------------------------------------------------ state as data

    def state(self) -> IsamState:
        """What a restarted worker needs to make the tree again (``isam_state.py``)."""
        keys, graph_T = _estimate(self._isam.calculateEstimate())
        walks = tuple(
            IsamWalkState(
                walk_id=w.walk_id,
                fingerprint=w.fingerprint,
                depth_scale=w.depth_scale,
                noise_scales=w.noise_scales.copy(),
                cost_alone=w.cost_alone,
                key_offset=w.key_offset,
                map_T_world=self._map_T_graph @ w.graph_T_world,
                keyframes=w.keyframes.copy(),
                map_T_keyframe=self._map_T_graph
                @ graph_T[_rows(keys, _POSE_KEY + w.key_offset + w.keyframes)],
                alone_tag_ids=np.array(sorted(w.alone_tags), dtype=np.int64),
                world_T_tag_alone=_stacked([w.alone_tags[t] for t in sorted(w.alone_tags)]),
            )
            for w in self._walks
        )
        tag_ids, map_T_tag = self._tags(keys, graph_T)
        return IsamState(
            walks=walks,
            tag_ids=tag_ids,
            map_T_tag=map_T_tag,
            params=self.params.to_dict(),
            next_key=self._next_key,
        )

    @classmethod
    def restore(
        cls, state: IsamState, walks: Sequence[Walk], params: SlamParams | None = None
    ) -> tuple[IsamBuilding, IncrementalMap]:
        """The tree made again from ``state`` and the walks' sessions (``walks``: the map's, in
        its order): each walk's factors from its session and stored fit, linearized at the
        stored optimum, one elimination. Raises :class:`StaleStateError` when ``state`` was not
        made from exactly these walks and parameters (the caller builds from scratch)."""
        params = params or SlamParams.from_dict(state.params)
        state.require_current(walks, params)
        clock = Clock()
        building = cls(params)
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        counts = []
        for s, (stored, walk) in enumerate(zip(state.walks, walks, strict=True)):
            screening = screen_detections(walk.session.detections, params)
            session = scaled_tag_depths(walk.session, stored.depth_scale)
            inputs = building._inputs(session, screening, stored.noise_scales)
            if not np.array_equal(inputs.keyframes, stored.keyframes):
                raise StaleStateError(
                    f"the incremental state is stale: walk {walk.walk_id!r} has other keyframes"
                )
            walk_graph = chain_graph(
                inputs, building._fixed, key_offset=stored.key_offset, gauge=s == 0
            )
            counts.append(int(walk_graph.size()))
            graph.push_back(walk_graph)
            for i, pose in zip(stored.keyframes.tolist(), stored.map_T_keyframe, strict=True):
                values.insert(X(stored.key_offset + i), to_pose3(pose))
            building._walks.append(
                WalkInTree(
                    walk_id=walk.walk_id,
                    fingerprint=stored.fingerprint,
                    session=session,
                    depth_scale=stored.depth_scale,
                    noise_scales=stored.noise_scales.copy(),
                    cost_alone=stored.cost_alone,
                    key_offset=stored.key_offset,
                    keyframes=inputs.keyframes,
                    graph_T_world=stored.map_T_world.copy(),
                    tag_ids=frozenset(inputs.tag_rows),
                    factor_indices=[],
                    screening=screening,
                    alone_tags=stored.alone_tag_poses(),
                )
            )
        for t, pose in zip(state.tag_ids.tolist(), state.map_T_tag, strict=True):
            values.insert(L(t), to_pose3(pose))
        building._next_key = state.next_key
        clock.lap("graph")
        result = building._isam.update(graph, values)
        building._take_indices(building._walks, counts, result)
        updates = building._settle()
        clock.lap("isam")
        return building, building.served(clock, updates)

    # ------------------------------------------------------------------ what is served

    def served(self, clock: Clock | None = None, updates: int = 0) -> IncrementalMap:
        """The map as it is served: the tags and every walk's poses in the map frame (the poses
        between keyframes by their interpolated correction, as the batch build places them).
        ``rounds``: the ISAM2 updates the last change took; ``relinearized``: none (the tree
        relinearizes variables, not walks)."""
        clock = clock or Clock()
        keys, graph_T = _estimate(self._isam.calculateEstimate())
        tag_ids, map_T_tag = self._tags(keys, graph_T)
        world_T_phone = []
        for w in self._walks:
            map_T_keyframe = (
                self._map_T_graph @ graph_T[_rows(keys, _POSE_KEY + w.key_offset + w.keyframes)]
            )
            raw = self._map_T_graph @ w.graph_T_world @ w.session.world_T_phone
            world_T_phone.append(
                interpolate_poses(raw, w.session.timestamp_s, w.keyframes, map_T_keyframe)
            )
        clock.lap("served")
        return IncrementalMap(
            walk_ids=self.walk_ids,
            tag_ids=tag_ids,
            map_T_tag=map_T_tag,
            world_T_phone=tuple(world_T_phone),
            rounds=updates,
            timings_ms=dict(clock.laps),
        )

    # ------------------------------------------------------------------ helpers

    def _inputs(
        self, session: Session, screening: Screening, noise_scales: FloatArray
    ) -> GraphInputs:
        return GraphInputs(
            session,
            self._fixed,
            screening=screening,
            noise_scales=np.asarray(noise_scales, dtype=np.float64)[None, :],
        )

    def _walk(
        self,
        walk: Walk,
        session: Session,
        screening: Screening,
        fit: WalkFit,
        inputs: GraphInputs,
        graph_T_world: FloatArray,
    ) -> WalkInTree:
        return WalkInTree(
            walk_id=walk.walk_id,
            fingerprint=walk_fingerprint(walk.session),
            session=session,
            depth_scale=fit.tag_depth_scale,
            noise_scales=np.array(fit.noise_scales, dtype=np.float64),
            cost_alone=float(fit.cost),
            key_offset=self._next_key,
            keyframes=inputs.keyframes,
            graph_T_world=np.array(graph_T_world, dtype=np.float64),
            tag_ids=frozenset(inputs.tag_rows),
            factor_indices=[],
            screening=screening,
            alone_tags=fit.alone.tag_poses(),
            fit=fit,
        )

    def _take_indices(
        self, walks: Sequence[WalkInTree], counts: Sequence[int], result: gtsam.ISAM2Result
    ) -> None:
        """Each walk's share of the factor indices an update gave its new factors, in order."""
        indices = [int(k) for k in result.getNewFactorsIndices()]
        start = 0
        for walk, count in zip(walks, counts, strict=True):
            walk.factor_indices = indices[start : start + count]
            start += count

    def _settle(self) -> int:
        """``ISAM2.update()`` until a call relinearizes no variable; the calls, the change's
        own included."""
        updates = 1
        while updates < MAX_UPDATES:
            result = self._isam.update()
            updates += 1
            if result.getVariablesRelinearized() == 0:
                break
        return updates

    def _relinearize_all(self) -> int:
        """The tree made anew from all its factors, linearized at its estimate; its updates.
        The factors keep their indices (the slots are refilled in order: no walk was removed)."""
        estimate = self._isam.calculateEstimate()
        factors = self._isam.getFactorsUnsafe()
        if factors.nrFactors() != factors.size():
            raise RuntimeError("a tree with removed factors cannot be made anew in place")
        self._isam = gtsam.ISAM2(self._isam.params())
        result = self._isam.update(factors, estimate)
        if [int(k) for k in result.getNewFactorsIndices()] != list(range(int(factors.size()))):
            raise RuntimeError("the tree made anew numbered its factors otherwise")
        return self._settle()

    def _map_tags(self) -> dict[int, FloatArray]:
        tag_ids = sorted(set().union(*(w.tag_ids for w in self._walks)))
        return {
            t: self._map_T_graph @ self._isam.calculateEstimatePose3(L(t)).matrix() for t in tag_ids
        }

    def _tags(self, keys: IntArray, graph_T: FloatArray) -> tuple[IntArray, FloatArray]:
        rows = np.flatnonzero((keys >> 56) == (_TAG_KEY >> 56))
        return keys[rows] - _TAG_KEY, self._map_T_graph @ graph_T[rows]


def _scaled_translations(world_T_phone: FloatArray, scale: float) -> FloatArray:
    """Poses with their translations × ``scale`` about the world's origin (how
    ``SessionAlignment.place`` scales a walk's odometry)."""
    scaled = np.array(world_T_phone, dtype=np.float64)
    scaled[..., :3, 3] *= scale
    return scaled


def _stacked(poses: Sequence[FloatArray]) -> FloatArray:
    return np.stack(poses) if poses else np.empty((0, 4, 4))


def _estimate(values: gtsam.Values) -> tuple[IntArray, FloatArray]:
    """Every variable's key (sorted, as ``Values`` keeps them) and pose, (V,) and (V, 4, 4)."""
    keys = np.array(list(values.keys()), dtype=np.int64)
    flat = gtsam.utilities.extractPose3(values)
    poses = np.zeros((len(keys), 4, 4))
    poses[:, :3, :3] = flat[:, :9].reshape(-1, 3, 3)
    poses[:, :3, 3] = flat[:, 9:]
    poses[:, 3, 3] = 1.0
    return keys, poses


def _rows(keys: IntArray, wanted: IntArray) -> IntArray:
    rows = np.searchsorted(keys, wanted)
    if np.any(rows >= len(keys)) or np.any(keys[np.minimum(rows, len(keys) - 1)] != wanted):
        raise KeyError("a walk's pose is not in the tree")
    return np.asarray(rows, dtype=np.int64)


def _initial(inputs: GraphInputs, tag_id: int) -> FloatArray:
    """A tag's start in the walk's world: its first used sighting (``GraphInputs.initial``)."""
    return np.asarray(inputs.initial.atPose3(L(tag_id)).matrix(), dtype=np.float64)


def _turn_and_shift(graph_T_phone: FloatArray, world_T_phone: FloatArray) -> FloatArray:
    """``world_T_graph``: the turn about +y and the translation taking the pose
    ``graph_T_phone`` to ``world_T_phone``'s heading and position (the frames share +y)."""
    yaw = yaw_of(world_T_phone[:3, :3] @ graph_T_phone[:3, :3].T)
    c, s = math.cos(yaw), math.sin(yaw)
    turn = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    return make_pose(turn, world_T_phone[:3, 3] - turn @ graph_T_phone[:3, 3])


def _require_placed(walks: Sequence[WalkInTree]) -> None:
    """Every walk shares at least ``MIN_SHARED_TAGS`` tags with the others, and the walks form
    one group through such tags (as a batch build of them would place them)."""
    if len(walks) < 2:
        return
    reached, frontier = {0}, [0]
    while frontier:
        s = frontier.pop()
        for o, other in enumerate(walks):
            if o not in reached and len(walks[s].tag_ids & other.tag_ids) >= MIN_SHARED_TAGS:
                reached.add(o)
                frontier.append(o)
    for s, walk in enumerate(walks):
        if s not in reached:
            others = frozenset().union(*(o.tag_ids for o in walks if o is not walk))
            shared = walk.tag_ids & others
            raise AlignmentError(
                walk.walk_id,
                "no_shared_tags" if not shared else "too_few_shared_tags",
                f"without the walk removed it shares tags {sorted(shared)} with the others",
            )


__all__ = ["MAX_UPDATES", "RELINEARIZE_THRESHOLD", "IsamBuilding"]
