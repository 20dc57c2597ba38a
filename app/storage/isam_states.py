"""A building map's incremental state (issue 38), stored with the map version it was made for.

    with db.transaction() as tx:                  # the version's own transaction
        version = maps.store_version(tx, ...)
        save_state(tx, map_id=7, map_version_id=version.id, state=building.state())
    with db.read() as tx:
        stored = current_state(tx, 7)             # None: the current version has none
    stored.state.require_current(walks, params)   # StaleStateError: build the batch way

An :class:`~app.domain.mapping.incremental.isam_state.IsamState` is one ``isam_state`` row and
one ``isam_walk_state`` row per walk (plain values and ``.npz`` bytes: ``IsamState.to_dict``).
Only the map's current version's state is ever read, so saving one deletes the map's others (a
map keeps one state, not one per version). A state is derivable (a batch build of the version's
walks makes it again), so backups do not carry it: a restored map's first change is a batch
build, and the ones after it are incremental again. Deleting a version or its map deletes its
state (foreign keys, ``ON DELETE CASCADE``).
"""

from __future__ import annotations

from dataclasses import dataclass

from sqlalchemy import delete, func, select
from sqlalchemy.orm import Session

from app.domain.mapping.incremental.isam_state import IsamState, IsamWalkState
from app.storage.orm import IsamStateRow, IsamWalkStateRow, MapVersion


@dataclass(frozen=True, slots=True, kw_only=True)
class StoredState:
    """The state of a map's current version: which version (id and number) and the state."""

    map_version_id: int
    version_number: int
    state: IsamState


def save_state(db_session: Session, *, map_id: int, map_version_id: int, state: IsamState) -> int:
    """Store ``state`` as version ``map_version_id``'s (in the caller's transaction, the one
    that stores the version), replacing every other state of map ``map_id``. Returns the bytes
    of arrays written."""
    db_session.execute(delete(IsamStateRow).where(IsamStateRow.map_id == map_id))
    row = state.to_dict()
    db_session.add(
        IsamStateRow(
            map_version_id=map_version_id,
            map_id=map_id,
            format=row["format"],
            fingerprint=row["fingerprint"],
            params=row["params"],
            walk_ids=row["walk_ids"],
            walk_fingerprints=row["walk_fingerprints"],
            next_key=row["next_key"],
            arrays=row["arrays"],
        )
    )
    db_session.flush()  # the walks' rows refer to it
    written = len(row["arrays"])
    for position, walk in enumerate(state.walks):
        walk_row = walk.to_dict()
        db_session.add(
            IsamWalkStateRow(
                map_version_id=map_version_id,
                position=position,
                walk_id=walk_row["walk_id"],
                fingerprint=walk_row["fingerprint"],
                depth_scale=walk_row["depth_scale"],
                cost_alone=walk_row["cost_alone"],
                key_offset=walk_row["key_offset"],
                arrays=walk_row["arrays"],
            )
        )
        written += len(walk_row["arrays"])
    db_session.flush()
    return written


def current_state(db_session: Session, map_id: int) -> StoredState | None:
    """The state stored with map ``map_id``'s current (newest) version; None when that version
    has none (a map of one session, a version built before, a batch build that made none).
    Raises ``StaleStateError`` when the rows do not make a state (another format, a walk's row
    not the one the state was made with)."""
    newest = db_session.execute(
        select(MapVersion.id, MapVersion.number)
        .where(MapVersion.map_id == map_id)
        .order_by(MapVersion.number.desc())
        .limit(1)
    ).first()
    if newest is None:
        return None
    version_id, number = int(newest[0]), int(newest[1])
    row = db_session.get(IsamStateRow, version_id)
    if row is None:
        return None
    walks = [
        IsamWalkState.from_dict(
            {
                "walk_id": w.walk_id,
                "fingerprint": w.fingerprint,
                "depth_scale": w.depth_scale,
                "cost_alone": w.cost_alone,
                "key_offset": w.key_offset,
                "arrays": w.arrays,
            }
        )
        for w in db_session.scalars(
            select(IsamWalkStateRow)
            .where(IsamWalkStateRow.map_version_id == version_id)
            .order_by(IsamWalkStateRow.position)
        )
    ]
    state = IsamState.from_dict(
        {
            "format": row.format,
            "fingerprint": row.fingerprint,
            "params": row.params,
            "walk_ids": row.walk_ids,
            "walk_fingerprints": row.walk_fingerprints,
            "next_key": row.next_key,
            "arrays": row.arrays,
        },
        walks,
    )
    return StoredState(map_version_id=version_id, version_number=number, state=state)


def state_count(db_session: Session, map_id: int | None = None) -> int:
    """States stored (of map ``map_id``; of every map)."""
    query = select(func.count()).select_from(IsamStateRow)
    if map_id is not None:
        query = query.where(IsamStateRow.map_id == map_id)
    return int(db_session.scalar(query) or 0)
