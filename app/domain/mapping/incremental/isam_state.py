"""What an ISAM2 building map keeps between versions, as data (issue 38).

The Bayes tree of gtsam's ``ISAM2`` cannot be stored; what it is made from can. The graph of a
building map is each walk's factors (``slam.chain_graph``), which its session and three things
learned from it alone fix: its screening (the parameters'), its tag depth scale and its noise
scales (its ``WalkFit``). With the optimum to linearize at, a restarted worker makes the tree
again in one elimination (``IsamBuilding.restore``), without optimizing any walk alone again.

So an :class:`IsamState` is one row per map version (the tags, the walks in order, the
parameters, the next free pose key) and one :class:`IsamWalkState` per walk (its fit's figures,
where its poses are keyed, its placement and its optimized keyframes, in the map frame). Both
serialize to plain values and ``.npz`` bytes (``np.load(..., allow_pickle=False)``), never
pickle:

    row, walk_rows = state.to_dict(), [w.to_dict() for w in state.walks]
    state = IsamState.from_dict(row, [IsamWalkState.from_dict(r) for r in walk_rows])
    state.require_current(walks, params)      # StaleStateError: build from scratch

A state remembers the fingerprint of every walk's data and of the parameters
(``state.walk_fingerprint``, ``state.building_fingerprint``, shared with the summary design):
used with other walks (one added or removed behind its back, one whose data changed) or other
parameters, it raises :class:`StaleStateError`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from app.domain.frames import FloatArray
from app.domain.mapping.params import SlamParams

from .state import (
    IntArray,
    StaleStateError,
    Walk,
    building_fingerprint,
    from_npz,
    full_poses,
    ordered_walk_rows,
    require_made_from,
    to_npz,
)

#: Version of the serialized form; :meth:`IsamState.from_dict` refuses any other.
ISAM_STATE_FORMAT = "isam-building/2"


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class IsamWalkState:
    """One walk of an ISAM2 building map, as its row stores it.

    walk_id, fingerprint: which walk, and :func:`walk_fingerprint` of its data.
    depth_scale: the factor on its camera-to-tag distances; noise_scales: (4,) the factors on
        its variances (``noise.COMPONENTS``), both from its data alone (its ``WalkFit``);
        cost_alone: its cost at its own optimum (what step 6's weighing compares with).
    key_offset: its phone pose ``i`` is the graph's ``X(key_offset + i)``.
    map_T_world: (4, 4) its world placed in the map frame (the poses between keyframes are
        its odometry placed there, corrected as the keyframes around them are).
    keyframes: (K,) its pose rows in the graph; map_T_keyframe: (K, 4, 4) their optimum, m.
    alone_tag_ids: (A,) the tags of its own map alone, sorted; world_T_tag_alone: (A, 4, 4) their
        poses there, in its own world, m: what the batch build places it by and tests its
        odometry scale on (``joint.placing``), so that the served map's report and the scale
        test's guard need no walk fitted again (``served_map.py``).
    """

    walk_id: str
    fingerprint: str
    depth_scale: float
    noise_scales: FloatArray
    cost_alone: float
    key_offset: int
    map_T_world: FloatArray
    keyframes: IntArray
    map_T_keyframe: FloatArray
    alone_tag_ids: IntArray
    world_T_tag_alone: FloatArray

    def alone_tag_poses(self) -> dict[int, FloatArray]:
        """Its own map's tags alone, by id, in its own world."""
        return {
            int(t): pose for t, pose in zip(self.alone_tag_ids, self.world_T_tag_alone, strict=True)
        }

    def to_dict(self) -> dict[str, Any]:
        """One table row: plain values and ``arrays`` (``.npz`` bytes)."""
        return {
            "walk_id": self.walk_id,
            "fingerprint": self.fingerprint,
            "depth_scale": self.depth_scale,
            "cost_alone": self.cost_alone,
            "key_offset": self.key_offset,
            "arrays": to_npz(
                noise_scales=self.noise_scales,
                map_T_world=self.map_T_world[:3, :],
                keyframes=self.keyframes,
                map_T_keyframe=self.map_T_keyframe[:, :3, :],
                alone_tag_ids=self.alone_tag_ids,
                world_T_tag_alone=self.world_T_tag_alone[:, :3, :],
            ),
        }

    @classmethod
    def from_dict(cls, row: Mapping[str, Any]) -> IsamWalkState:
        arrays = from_npz(row["arrays"])
        return cls(
            walk_id=str(row["walk_id"]),
            fingerprint=str(row["fingerprint"]),
            depth_scale=float(row["depth_scale"]),
            cost_alone=float(row["cost_alone"]),
            key_offset=int(row["key_offset"]),
            noise_scales=arrays["noise_scales"],
            map_T_world=full_poses(arrays["map_T_world"]),
            keyframes=arrays["keyframes"].astype(np.int64),
            map_T_keyframe=full_poses(arrays["map_T_keyframe"]),
            alone_tag_ids=arrays["alone_tag_ids"].astype(np.int64),
            world_T_tag_alone=full_poses(arrays["world_T_tag_alone"]),
        )


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class IsamState:
    """An ISAM2 building map as a restarted worker needs it (the module docstring).

    walks: in the map's order (the first walk's world is the map frame; its first pose holds
        the gauge). tag_ids: (T,) sorted; map_T_tag: (T, 4, 4), m.
    params: ``SlamParams.to_dict()`` everything was made with. next_key: the first pose key no
        walk has used (a walk added next is keyed from there).
    """

    walks: tuple[IsamWalkState, ...]
    tag_ids: IntArray
    map_T_tag: FloatArray
    params: Mapping[str, Any]
    next_key: int

    @property
    def walk_ids(self) -> tuple[str, ...]:
        return tuple(w.walk_id for w in self.walks)

    @property
    def fingerprint(self) -> str:
        """:func:`building_fingerprint` of the walks and parameters this state was made from."""
        return building_fingerprint(
            [(w.walk_id, w.fingerprint) for w in self.walks], SlamParams.from_dict(self.params)
        )

    def require_current(self, walks: Sequence[Walk], params: SlamParams) -> None:
        """Raise :class:`StaleStateError` unless this state was made from exactly ``walks`` (in
        this order, with these data) and ``params``: the caller then builds from scratch."""
        require_made_from(self.walk_ids, self.fingerprint, walks, params)

    def to_dict(self) -> dict[str, Any]:
        """The building's row; the walks' are rows of their own (``walks[k].to_dict()``)."""
        return {
            "format": ISAM_STATE_FORMAT,
            "fingerprint": self.fingerprint,
            "params": dict(self.params),
            "walk_ids": list(self.walk_ids),
            "walk_fingerprints": [w.fingerprint for w in self.walks],
            "next_key": self.next_key,
            "arrays": to_npz(tag_ids=self.tag_ids, map_T_tag=self.map_T_tag[:, :3, :]),
        }

    @classmethod
    def from_dict(cls, row: Mapping[str, Any], walks: Sequence[IsamWalkState]) -> IsamState:
        """Inverse of :meth:`to_dict` with the walks' rows (any order). Raises
        :class:`StaleStateError` when the rows are not the ones the building row was made
        with."""
        ordered = ordered_walk_rows(row, walks, ISAM_STATE_FORMAT, "row")
        arrays = from_npz(row["arrays"])
        state = cls(
            walks=ordered,
            tag_ids=arrays["tag_ids"].astype(np.int64),
            map_T_tag=full_poses(arrays["map_T_tag"]),
            params=dict(row["params"]),
            next_key=int(row["next_key"]),
        )
        if state.fingerprint != row["fingerprint"]:
            raise StaleStateError("the state's fingerprint does not match its walks and params")
        return state

    def size_bytes(self) -> int:
        """What the rows take as stored, roughly (their arrays and plain values)."""
        rows = [self.to_dict(), *(w.to_dict() for w in self.walks)]
        return sum(len(r["arrays"]) + len(repr({**r, "arrays": b""})) for r in rows)
