"""What an incremental building map keeps between versions, as data (issue 38).

A :class:`BuildingState` is one row per map version (the tags, the walks' placements, which walks
in which order, the parameters) and one :class:`WalkSummary` per walk (its pose chain condensed
to a Gaussian on its tags, in its own world frame). Adding a walk writes the new walk's summary
and the building row; the summaries of the walks already there are rewritten only for the walks
whose tags moved enough to be relinearized. Both serialize to plain values and ``.npz`` bytes
(``np.load(..., allow_pickle=False)``), never pickle:

    row = state.to_dict()                 # {"format", "params", "walk_ids", …, "arrays": bytes}
    rows = [w.to_dict() for w in state.walks]   # one per walk: {"walk_id", …, "arrays": bytes}
    state = BuildingState.from_dict(row, [WalkSummary.from_dict(r) for r in rows])

A state remembers the fingerprint of every walk's data and of the parameters it was made from
(:func:`walk_fingerprint`, :func:`building_fingerprint`): a caller compares it with the map's
current walks (:func:`require_current`) and builds from scratch when they differ (a walk added
behind the state's back, changed parameters).
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol, TypeVar

import numpy as np
import numpy.typing as npt

from app.domain.errors import InvisibleMapError
from app.domain.frames import FloatArray
from app.domain.mapping.params import SlamParams
from app.domain.upload.session import Session, TagDetections

IntArray = npt.NDArray[np.int64]

#: Version of the serialized form; :meth:`BuildingState.from_dict` refuses any other.
STATE_FORMAT = "incremental-building/1"


class _WalkRow(Protocol):
    """A walk's row of either design's state: which walk, and its data's fingerprint."""

    @property
    def walk_id(self) -> str: ...

    @property
    def fingerprint(self) -> str: ...


WalkRowT = TypeVar("WalkRowT", bound=_WalkRow)


class StaleStateError(InvisibleMapError):
    """Raised when a state was not made from the walks and parameters it is used with (a walk
    added or changed behind its back, other parameters): build the map from scratch."""


@dataclass(frozen=True, slots=True, kw_only=True)
class Walk:
    """A walk of the building: its id in the map (unique) and its session."""

    walk_id: str
    session: Session


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class WalkSummary:
    """One walk condensed to its tags (the "summary factor"), in the walk's own world frame.

    The walk's factors (odometry, gravity, tag sightings under their Huber weights, the prior that
    pins its first pose's heading and position) linearized at ``world_T_tag`` and the poses that
    fit those tags best, and its poses marginalized: the walk's cost as a function of its tags is
    ``cost + δᵀ information δ / 2 − gradient · δ`` (gtsam's error, half the χ²), with
    ``δ = Log(world_T_tag⁻¹ · world_T_tag')`` per tag, stacked in ``tag_ids`` order, each
    ``[rot rad, trans m]``.

    walk_id, fingerprint: which walk, and :func:`walk_fingerprint` of its data.
    noise_scales: (4,) the factors on its variances (``noise.COMPONENTS``): its own data's.
    depth_scale: the factor on its camera-to-tag distances (``joint.tag_depth_scale``).
    tag_ids: (n,) its tags; world_T_tag: (n, 4, 4) where they were linearized, its world, m.
    information: (6n, 6n); gradient: (6n,).
    keyframes: (K,) its pose rows in the graph; world_T_phone: (N, 4, 4) every pose, best fitting
        ``world_T_tag``, its world frame.
    firmness: (n,) Σ over its used sightings of each tag of 1 / (position variance factor · d²),
        how firmly it holds each tag (``joint._redundancy_gain``'s weights).
    cost: its odometry and tag factors' χ² at the linearization point (``slam.chain_costs``);
        cost_alone: the same at its own optimum.
    relinearized: how many times it was linearized again since it was first summarized.
    """

    walk_id: str
    fingerprint: str
    noise_scales: FloatArray
    depth_scale: float
    tag_ids: IntArray
    world_T_tag: FloatArray
    information: FloatArray
    gradient: FloatArray
    keyframes: IntArray
    world_T_phone: FloatArray
    firmness: FloatArray
    cost: float
    cost_alone: float
    relinearized: int = 0

    def to_dict(self) -> dict[str, Any]:
        """One table row: plain values and ``arrays`` (``.npz`` bytes)."""
        return {
            "walk_id": self.walk_id,
            "fingerprint": self.fingerprint,
            "depth_scale": self.depth_scale,
            "cost": self.cost,
            "cost_alone": self.cost_alone,
            "relinearized": self.relinearized,
            "arrays": to_npz(
                noise_scales=self.noise_scales,
                tag_ids=self.tag_ids,
                world_T_tag=self.world_T_tag[:, :3, :],
                information=self.information,
                gradient=self.gradient,
                keyframes=self.keyframes,
                world_T_phone=self.world_T_phone[:, :3, :],
                firmness=self.firmness,
            ),
        }

    @classmethod
    def from_dict(cls, row: Mapping[str, Any]) -> WalkSummary:
        arrays = from_npz(row["arrays"])
        return cls(
            walk_id=str(row["walk_id"]),
            fingerprint=str(row["fingerprint"]),
            depth_scale=float(row["depth_scale"]),
            cost=float(row["cost"]),
            cost_alone=float(row["cost_alone"]),
            relinearized=int(row["relinearized"]),
            noise_scales=arrays["noise_scales"],
            tag_ids=arrays["tag_ids"].astype(np.int64),
            world_T_tag=full_poses(arrays["world_T_tag"]),
            information=arrays["information"],
            gradient=arrays["gradient"],
            keyframes=arrays["keyframes"].astype(np.int64),
            world_T_phone=full_poses(arrays["world_T_phone"]),
            firmness=arrays["firmness"],
        )


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class BuildingState:
    """The building map as the next add or removal needs it.

    walks: the summaries, in the map's order (the first walk's world is the map frame).
    map_T_world: (S, 4, 4) each walk's placement (a turn about +y and a translation; the first
        is the identity). tag_ids: (T,) sorted; map_T_tag: (T, 4, 4), m.
    params: the parameters (``SlamParams.to_dict()``) everything was made with.
    """

    walks: tuple[WalkSummary, ...]
    map_T_world: FloatArray
    tag_ids: IntArray
    map_T_tag: FloatArray
    params: Mapping[str, Any]

    @property
    def walk_ids(self) -> tuple[str, ...]:
        return tuple(w.walk_id for w in self.walks)

    @property
    def fingerprint(self) -> str:
        """:func:`building_fingerprint` of the walks and parameters this state was made from."""
        return building_fingerprint(
            [(w.walk_id, w.fingerprint) for w in self.walks], SlamParams.from_dict(self.params)
        )

    def walk(self, walk_id: str) -> WalkSummary:
        for w in self.walks:
            if w.walk_id == walk_id:
                return w
        raise KeyError(f"no walk {walk_id!r} in the building")

    def to_dict(self) -> dict[str, Any]:
        """The building's row; the walks' summaries are rows of their own
        (``walks[k].to_dict()``)."""
        return {
            "format": STATE_FORMAT,
            "fingerprint": self.fingerprint,
            "params": dict(self.params),
            "walk_ids": list(self.walk_ids),
            "walk_fingerprints": [w.fingerprint for w in self.walks],
            "arrays": to_npz(
                map_T_world=self.map_T_world[:, :3, :],
                tag_ids=self.tag_ids,
                map_T_tag=self.map_T_tag[:, :3, :],
            ),
        }

    @classmethod
    def from_dict(cls, row: Mapping[str, Any], walks: Sequence[WalkSummary]) -> BuildingState:
        """Inverse of :meth:`to_dict` with the walks' rows (any order). Raises
        :class:`StaleStateError` when the rows are not the ones the building row was made with."""
        ordered = ordered_walk_rows(row, walks, STATE_FORMAT, "summary row")
        arrays = from_npz(row["arrays"])
        state = cls(
            walks=ordered,
            map_T_world=full_poses(arrays["map_T_world"]),
            tag_ids=arrays["tag_ids"].astype(np.int64),
            map_T_tag=full_poses(arrays["map_T_tag"]),
            params=dict(row["params"]),
        )
        if state.fingerprint != row["fingerprint"]:
            raise StaleStateError("the state's fingerprint does not match its walks and params")
        return state

    def evolve(self, **changes: Any) -> BuildingState:
        return dataclasses.replace(self, **changes)


def walk_fingerprint(session: Session) -> str:
    """SHA-256 of everything of ``session`` a map is made from (poses, times, detections)."""
    digest = hashlib.sha256()
    for array in (session.pose_id, session.timestamp_s, session.world_T_phone):
        digest.update(np.ascontiguousarray(array).tobytes())
    for f in dataclasses.fields(TagDetections):
        digest.update(f.name.encode())
        digest.update(np.ascontiguousarray(getattr(session.detections, f.name)).tobytes())
    return digest.hexdigest()


def building_fingerprint(walks: Sequence[tuple[str, str]], params: SlamParams) -> str:
    """SHA-256 of the walks ((walk id, :func:`walk_fingerprint`), in the map's order: the first
    is the map frame) and the parameters."""
    text = json.dumps(
        {"walks": [list(w) for w in walks], "params": params.to_dict()}, sort_keys=True
    )
    return hashlib.sha256(text.encode()).hexdigest()


def require_current(state: BuildingState, walks: Sequence[Walk], params: SlamParams) -> None:
    """Raise :class:`StaleStateError` unless ``state`` was made from exactly ``walks`` (in this
    order, with these data) and ``params``: the caller then builds from scratch."""
    require_made_from(state.walk_ids, state.fingerprint, walks, params)


def require_made_from(
    walk_ids: Sequence[str], fingerprint: str, walks: Sequence[Walk], params: SlamParams
) -> None:
    """Raise :class:`StaleStateError` unless a state of ``walk_ids`` whose
    :func:`building_fingerprint` is ``fingerprint`` was made from exactly ``walks`` (in this
    order, with these data) and ``params`` (either design's state)."""
    made, given = list(walk_ids), [w.walk_id for w in walks]
    if made != given:
        raise StaleStateError(
            f"the incremental state is stale: it holds walks {made}, the map has {given}"
        )
    current = building_fingerprint(
        [(w.walk_id, walk_fingerprint(w.session)) for w in walks], params
    )
    if current != fingerprint:
        raise StaleStateError(
            "the incremental state is stale: a walk's data or the parameters changed"
        )


def ordered_walk_rows(
    row: Mapping[str, Any], walks: Sequence[WalkRowT], state_format: str, what: str
) -> tuple[WalkRowT, ...]:
    """The walks' rows ``walks`` (any order) in the order of the building's ``row``, checked
    against it: StaleStateError for another ``state_format``, a walk without a row, or a row
    (``what``) whose fingerprint is not the one the building row was made with."""
    if row.get("format") != state_format:
        raise StaleStateError(f"unknown state format {row.get('format')!r}")
    by_id = {w.walk_id: w for w in walks}
    ids = [str(w) for w in row["walk_ids"]]
    missing = [w for w in ids if w not in by_id]
    if missing:
        raise StaleStateError(f"no {what} for walks {missing}")
    ordered = tuple(by_id[w] for w in ids)
    if [w.fingerprint for w in ordered] != list(row["walk_fingerprints"]):
        raise StaleStateError(f"a walk's {what} is not the one this state was made with")
    return ordered


def to_npz(**arrays: npt.NDArray[Any]) -> bytes:
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)  # type: ignore[arg-type]
    return buffer.getvalue()


def from_npz(data: bytes) -> dict[str, npt.NDArray[Any]]:
    with np.load(io.BytesIO(data), allow_pickle=False) as npz:
        return {name: np.array(npz[name]) for name in npz.files}


def full_poses(top: FloatArray) -> FloatArray:
    """(…, 4, 4) from the top three rows (…, 3, 4)."""
    out = np.zeros((*top.shape[:-2], 4, 4))
    out[..., :3, :] = top
    out[..., 3, 3] = 1.0
    return out
