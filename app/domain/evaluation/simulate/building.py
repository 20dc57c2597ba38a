"""The procedural building: :class:`Building`, the corridor grid with its staircase, free space
and tags on the walls (``build_building``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.domain.frames import FloatArray

from .config import (
    CEILING_HEIGHT_M,
    JUNCTION_CLEARANCE_M,
    STAIR_FLIGHT_SPACING_M,
    STAIR_RISE_PER_RUN,
    STAIRWELL_MARGIN_M,
    IntArray,
    SimulationConfig,
)


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class Building:
    """The procedural building: a walk graph of corridors, the free space, and the tags.

    node_xyz_m: (K, 3) corridor junctions at floor level, world frame (y up), m.
    edge_nodes: (E, 2) the two nodes each walkable edge joins (a corridor stretch or the stairs).
    edge_polylines_m: E arrays (P_e, 3), the floor-level centreline from ``edge_nodes[e, 0]`` to
        ``edge_nodes[e, 1]``, m.
    free_space_boxes_m: (B, 2, 3) min and max corners of axis-aligned boxes whose union is the air
        inside the building (corridors, stairwell); a line of sight must stay inside it.
    world_T_tag: tag id → (4, 4) tag pose; +z out of the wall into the corridor, +y up.
    corridor_tag_ids: per straight corridor (per floor), its tag ids in order along it.
    tag_offset_along_m: tag id → distance of the tag from its corridor's start, m.
    floor_heights_m: height of each floor, m.
    """

    node_xyz_m: FloatArray
    edge_nodes: IntArray
    edge_polylines_m: tuple[FloatArray, ...]
    free_space_boxes_m: FloatArray
    world_T_tag: dict[int, FloatArray]
    corridor_tag_ids: tuple[tuple[int, ...], ...]
    tag_offset_along_m: dict[int, float]
    floor_heights_m: tuple[float, ...]


# --------------------------------------------------------------------------- building


def build_building(config: SimulationConfig, rng: np.random.Generator) -> Building:
    """The corridor grid (one or two floors), its stairs, free space and tags."""
    nx, nz = config.blocks
    bx, bz = config.block_size_m
    half_width_m = config.corridor_width_m / 2
    floors = [0.0, config.floor_height_m] if config.two_floors else [0.0]
    nodes_per_floor = (nx + 1) * (nz + 1)

    def node(floor: int, i: int, j: int) -> int:
        return floor * nodes_per_floor + j * (nx + 1) + i

    node_xyz = np.array(
        [[i * bx, y, j * bz] for y in floors for j in range(nz + 1) for i in range(nx + 1)],
        dtype=np.float64,
    )
    edges: list[tuple[int, int]] = []
    for f in range(len(floors)):
        edges += [(node(f, i, j), node(f, i + 1, j)) for j in range(nz + 1) for i in range(nx)]
        edges += [(node(f, i, j), node(f, i, j + 1)) for i in range(nx + 1) for j in range(nz)]
    polylines = [node_xyz[[a, b]] for a, b in edges]

    boxes: list[list[list[float]]] = []
    for y in floors:
        top = y + CEILING_HEIGHT_M
        for j in range(nz + 1):  # corridors along x
            z = j * bz
            boxes.append(
                [
                    [-half_width_m, y, z - half_width_m],
                    [nx * bx + half_width_m, top, z + half_width_m],
                ]
            )
        for i in range(nx + 1):  # corridors along z
            x = i * bx
            boxes.append(
                [
                    [x - half_width_m, y, -half_width_m],
                    [x + half_width_m, top, nz * bz + half_width_m],
                ]
            )

    if config.two_floors:
        stairs, stairwell = _staircase(config, node_xyz[node(0, nx, 0)])
        edges.append((node(0, nx, 0), node(1, nx, 0)))
        polylines.append(stairs)
        boxes.append(stairwell)

    world_T_tag, corridor_tag_ids, offset_along = _place_tags(config, floors, rng)
    return Building(
        node_xyz_m=node_xyz,
        edge_nodes=np.array(edges, dtype=np.int64),
        edge_polylines_m=tuple(polylines),
        free_space_boxes_m=np.array(boxes, dtype=np.float64),
        world_T_tag=world_T_tag,
        corridor_tag_ids=corridor_tag_ids,
        tag_offset_along_m=offset_along,
        floor_heights_m=tuple(floors),
    )


def _staircase(
    config: SimulationConfig, bottom_xyz_m: FloatArray
) -> tuple[FloatArray, list[list[float]]]:
    """Switch-back stairs out of the building's east door: the centreline and the stairwell box."""
    x0, y0, z0 = (float(v) for v in bottom_xyz_m)
    rise_m = config.floor_height_m / 2
    run_m = rise_m / STAIR_RISE_PER_RUN
    door_x = x0 + config.corridor_width_m / 2
    foot_x = door_x + JUNCTION_CLEARANCE_M
    back_z = z0 - STAIR_FLIGHT_SPACING_M
    # fmt: off
    centreline = np.array([
        [x0,             y0,                         z0],
        [foot_x,         y0,                         z0],
        [foot_x + run_m, y0 + rise_m,                z0],      # first flight, going east
        [foot_x + run_m, y0 + rise_m,                back_z],  # landing
        [foot_x,         y0 + config.floor_height_m, back_z],  # second flight, going west
        [foot_x,         y0 + config.floor_height_m, z0],
        [x0,             y0 + config.floor_height_m, z0],
    ])
    # fmt: on
    stairwell = [
        [door_x, y0, back_z - STAIRWELL_MARGIN_M],
        [
            foot_x + run_m + STAIRWELL_MARGIN_M,
            y0 + config.floor_height_m + CEILING_HEIGHT_M,
            z0 + config.corridor_width_m / 2,
        ],
    ]
    return centreline, stairwell


def _place_tags(
    config: SimulationConfig, floors: list[float], rng: np.random.Generator
) -> tuple[dict[int, FloatArray], tuple[tuple[int, ...], ...], dict[int, float]]:
    """Tags along every corridor, ``tag_spacing_m`` apart, on a random wall, away from junctions."""
    nx, nz = config.blocks
    bx, bz = config.block_size_m
    half_width_m = config.corridor_width_m / 2
    clearance_m = half_width_m + JUNCTION_CLEARANCE_M
    up = np.array([0.0, 1.0, 0.0])

    # (start point at floor level, unit direction, length, spacing of crossings)
    corridors: list[tuple[FloatArray, FloatArray, float, float]] = []
    for y in floors:
        for j in range(nz + 1):
            corridors.append((np.array([0.0, y, j * bz]), np.array([1.0, 0.0, 0.0]), nx * bx, bx))
        for i in range(nx + 1):
            corridors.append((np.array([i * bx, y, 0.0]), np.array([0.0, 0.0, 1.0]), nz * bz, bz))

    world_T_tag: dict[int, FloatArray] = {}
    offset_along: dict[int, float] = {}
    corridor_tag_ids: list[tuple[int, ...]] = []
    for start, direction, length_m, crossing_m in corridors:
        crossings = np.arange(0.0, length_m + 1e-9, crossing_m)
        zones = [(c - clearance_m, c + clearance_m) for c in crossings]
        ids: list[int] = []
        for along_m in _tag_offsets(config.tag_spacing_m, length_m - clearance_m, zones, rng):
            side = 1.0 if rng.random() < 0.5 else -1.0
            lateral = np.cross(up, direction)  # horizontal, perpendicular to the corridor
            height_m = rng.uniform(*config.tag_height_m)
            world_t_tag = start + along_m * direction + side * half_width_m * lateral
            world_t_tag = world_t_tag + height_m * up
            normal = -side * lateral  # out of the wall, into the corridor
            world_T = np.eye(4)
            world_T[:3, 0] = np.cross(up, normal)
            world_T[:3, 1] = up
            world_T[:3, 2] = normal
            world_T[:3, 3] = world_t_tag
            tag_id = len(world_T_tag)
            world_T_tag[tag_id] = world_T
            offset_along[tag_id] = float(along_m)
            ids.append(tag_id)
        corridor_tag_ids.append(tuple(ids))
    return world_T_tag, tuple(corridor_tag_ids), offset_along


def _tag_offsets(
    spacing_m: tuple[float, float],
    end_m: float,
    zones: list[tuple[float, float]],
    rng: np.random.Generator,
) -> list[float]:
    """Positions along a corridor: gaps uniform in ``spacing_m``, never inside a junction zone."""
    low, high = spacing_m
    offsets: list[float] = []
    previous = zones[0][1] - low  # the first tag lands in [zone end, zone end + (high − low)]
    while True:
        window = _subtract_intervals(previous + low, min(previous + high, end_m), zones)
        if not window:  # a junction zone fills the window (tiny blocks): skip past it
            after = [hi for lo, hi in zones if lo <= previous + high and hi > previous + low]
            if not after or max(after) > end_m:
                return offsets
            window = [(max(after), max(after))]
        lengths = np.array([hi - lo for lo, hi in window])
        if lengths.sum() <= 0:
            pick = window[0][0]
        else:
            u = rng.uniform(0.0, float(lengths.sum()))
            k = int(np.searchsorted(np.cumsum(lengths), u, side="right"))
            k = min(k, len(window) - 1)
            pick = window[k][0] + (u - float(lengths[:k].sum()))
        offsets.append(pick)
        previous = pick


def _subtract_intervals(
    lo: float, hi: float, holes: list[tuple[float, float]]
) -> list[tuple[float, float]]:
    """[lo, hi] minus the union of ``holes``, as sorted closed intervals (maybe empty)."""
    if hi < lo:
        return []
    pieces = [(lo, hi)]
    for hole_lo, hole_hi in holes:
        next_pieces = []
        for a, b in pieces:
            if hole_hi <= a or hole_lo >= b:
                next_pieces.append((a, b))
                continue
            if hole_lo > a:
                next_pieces.append((a, hole_lo))
            if hole_hi < b:
                next_pieces.append((hole_hi, b))
        pieces = next_pieces
    return pieces
