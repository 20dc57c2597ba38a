"""Which change of a building map the ISAM2 engine can make from a stored state (issue 38).

    change = one_walk_change(state, walks, params)   # str: why the change is a batch build's
    building, served = apply_change(state, change, params)

A stored :class:`IsamState` is of the walks of the map's current version. The map's next version
can be made from it when its walks are the state's with exactly one walk added last, or with
exactly one taken out (the others in the same order), and the state is current for the walks it
shares with them (``IsamState.require_current``: the same walks, data and parameters). Anything
else — two walks added (one behind the state's back), another order, other parameters, a walk's
data changed — is a batch build's.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from app.domain.mapping.params import SlamParams

from .isam import IsamBuilding
from .isam_state import IsamState
from .state import StaleStateError, Walk
from .updates import IncrementalMap


@dataclass(frozen=True, slots=True, kw_only=True)
class WalkChange:
    """One walk added to or taken out of the state's walks.

    before: the state's walks (the one taken out among them), in its order.
    added: the walk added last (None for a removal); removed: the walk id taken out (None for
        an add).
    """

    before: tuple[Walk, ...]
    added: Walk | None = None
    removed: str | None = None

    @property
    def summary(self) -> str:
        return (
            f"{self.added.walk_id} added" if self.added is not None else f"{self.removed} taken out"
        )


def one_walk_change(
    state: IsamState,
    walk_ids: Sequence[str],
    params: SlamParams,
    sessions: Mapping[str, Walk],
) -> WalkChange | str:
    """The change from ``state``'s walks to ``walk_ids`` (the map's next version's, in order),
    if the engine can make it; else why not (the caller builds the batch way). ``sessions``:
    the walks by id, every one of ``walk_ids`` and, for a removal, the one taken out (its
    factors are made from its session to be taken out again)."""
    held, wanted = list(state.walk_ids), list(walk_ids)
    added: str | None = None
    removed: str | None = None
    if len(wanted) == len(held) + 1 and wanted[:-1] == held:
        added = wanted[-1]
    elif len(wanted) == len(held) - 1 and len(wanted) >= 2:
        gone = [w for w in held if w not in wanted]
        if len(gone) != 1 or [w for w in held if w != gone[0]] != wanted:
            return f"not one walk taken out of {held}: {wanted}"
        removed = gone[0]
    elif wanted == held:
        return "the same walks (a rebuild)"
    else:
        return f"not one walk added to or taken out of {held}: {wanted}"
    missing = [w for w in [*held, *([added] if added else [])] if w not in sessions]
    if missing:
        return f"walks {missing} are not at hand"
    before = tuple(sessions[w] for w in held)
    try:
        state.require_current(before, params)
    except StaleStateError as err:
        return str(err)
    return WalkChange(
        before=before, added=None if added is None else sessions[added], removed=removed
    )


def apply_change(
    state: IsamState, change: WalkChange, params: SlamParams
) -> tuple[IsamBuilding, IncrementalMap, dict[str, float]]:
    """The tree made again from ``state`` (``IsamBuilding.restore``) and ``change`` made in it;
    the served map and the wall-clock time each took, ms (``restore``, ``change``). Raises
    ``StaleStateError`` (restore) and ``AlignmentError`` (a walk no tags place)."""
    started_s = time.perf_counter()
    building, _ = IsamBuilding.restore(state, change.before, params)
    restored_s = time.perf_counter()
    served = (
        building.add(change.added)
        if change.added is not None
        else building.remove(str(change.removed))
    )
    timings_ms = {
        "restore": (restored_s - started_s) * 1e3,
        "change": (time.perf_counter() - restored_s) * 1e3,
    }
    return building, served, timings_ms


__all__ = ["WalkChange", "apply_change", "one_walk_change"]
