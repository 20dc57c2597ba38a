"""The walk: the true phone trajectory through a building (``walk_route``): the route along the
corridors, the gait, the sway and where the phone looks."""

from __future__ import annotations

import heapq
import math

import numpy as np

from app.domain.frames import FloatArray

from .building import Building
from .config import (
    ATTENTION_CORRELATION_S,
    ATTENTION_RANGE_M,
    ATTENTION_THRESHOLD,
    BOB_AMPLITUDE_M,
    CEILING_HEIGHT_M,
    HAND_CORRELATION_S,
    LOOK_AROUND_CORRELATION_S,
    LOOK_SMOOTHING_S,
    MAX_LOOK_RAD,
    MAX_SWAY_M,
    PAIR_CHUNK,
    PHONE_AHEAD_M,
    PITCH_NOISE_RAD,
    ROLL_NOISE_RAD,
    STEP_FREQUENCY_HZ,
    SWAY_CORRELATION_S,
    SWAY_M,
    TURN_SMOOTHING_S,
    IntArray,
    SimulationConfig,
)
from .numeric import (
    gaussian_kernel,
    gaussian_smooth,
    rotations_about_x,
    rotations_about_y,
    rotations_about_z,
    smooth_noise,
)

# --------------------------------------------------------------------------- the walk


def walk_route(
    config: SimulationConfig, building: Building, rng: np.random.Generator
) -> FloatArray:
    """(N, 4, 4) true ``world_T_phone`` along a coverage walk of the building."""
    n = config.num_poses
    step_m = config.speed_m_per_s / config.rate_hz
    pad = math.ceil(3 * TURN_SMOOTHING_S * config.rate_hz)
    n_route = n + 2 * pad
    vertices = route(
        building,
        (n_route - 1) * step_m + step_m,
        rng,
        max_floor_changes=config.max_floor_changes,
    )

    segment = np.diff(vertices, axis=0)
    cumulative_m = np.concatenate([[0.0], np.cumsum(np.linalg.norm(segment, axis=1))])
    along_m = np.arange(n_route) * step_m
    body_route = np.stack(
        [np.interp(along_m, cumulative_m, vertices[:, k]) for k in range(3)], axis=1
    )
    k_segment = np.clip(
        np.searchsorted(cumulative_m, along_m, side="right") - 1, 0, len(segment) - 1
    )
    heading_route = np.unwrap(np.arctan2(-segment[k_segment, 0], -segment[k_segment, 2]))

    kernel = gaussian_kernel(TURN_SMOOTHING_S * config.rate_hz, pad)
    body = np.stack([np.convolve(body_route[:, k], kernel, mode="valid") for k in range(3)], axis=1)
    heading_rad = np.convolve(heading_route, kernel, mode="valid")

    time_s = np.arange(n) / config.rate_hz
    look_rad = _look_direction(config, building, body, heading_rad, rng)
    pitch_rad = smooth_noise(rng, n, PITCH_NOISE_RAD, HAND_CORRELATION_S * config.rate_hz)
    roll_rad = math.radians(config.phone_roll_deg) + smooth_noise(
        rng, n, ROLL_NOISE_RAD, HAND_CORRELATION_S * config.rate_hz
    )
    sway_m = np.clip(
        smooth_noise(rng, n, SWAY_M, SWAY_CORRELATION_S * config.rate_hz),
        -MAX_SWAY_M,
        MAX_SWAY_M,
    )
    forward = np.stack([-np.sin(heading_rad), np.zeros(n), -np.cos(heading_rad)], axis=1)
    left = np.stack([-np.cos(heading_rad), np.zeros(n), np.sin(heading_rad)], axis=1)
    bob_m = BOB_AMPLITUDE_M * np.sin(2 * math.pi * STEP_FREQUENCY_HZ * time_s)

    world_T_phone = np.zeros((n, 4, 4))
    world_T_phone[:, :3, :3] = (
        rotations_about_y(heading_rad + look_rad)
        @ rotations_about_x(pitch_rad)
        @ rotations_about_z(roll_rad)
    )
    world_T_phone[:, :3, 3] = body + PHONE_AHEAD_M * forward + sway_m[:, None] * left
    world_T_phone[:, 1, 3] += config.phone_height_m + bob_m
    world_T_phone[:, 3, 3] = 1.0
    return world_T_phone


def _look_direction(
    config: SimulationConfig,
    building: Building,
    body_xyz_m: FloatArray,
    heading_rad: FloatArray,
    rng: np.random.Generator,
) -> FloatArray:
    """(N,) yaw of the phone off the walking direction, rad.

    While paying attention (70% of the time, in spells of a few seconds) the walker
    points the phone at the nearest tag ahead that faces them, within ``ATTENTION_RANGE_M``;
    otherwise the phone swings smoothly left and right. Turns are smoothed.
    """
    n = body_xyz_m.shape[0]
    rate_hz = config.rate_hz
    swing_rad = smooth_noise(rng, n, config.look_around_rad, LOOK_AROUND_CORRELATION_S * rate_hz)
    attention = smooth_noise(rng, n, 1.0, ATTENTION_CORRELATION_S * rate_hz)
    attentive = (attention > ATTENTION_THRESHOLD) & config.look_at_tags
    world_T_tags = np.stack([building.world_T_tag[t] for t in sorted(building.world_T_tag)])
    tag_xyz, tag_normal = world_T_tags[:, :3, 3], world_T_tags[:, :3, 2]
    target_rad = swing_rad.copy()
    for start in range(0, n, PAIR_CHUNK):
        stop = min(start + PAIR_CHUNK, n)
        to_tag = tag_xyz[None, :, :] - body_xyz_m[start:stop, None, :]  # (n, T, 3)
        horizontal_m = np.hypot(to_tag[..., 0], to_tag[..., 2])
        # Bearing of the tag off the heading: the heading ψ looks along (−sin ψ, −cos ψ) in x–z.
        bearing = np.arctan2(-to_tag[..., 0], -to_tag[..., 2]) - heading_rad[start:stop, None]
        bearing = (bearing + math.pi) % (2 * math.pi) - math.pi
        facing = np.einsum("ntk,tk->nt", -to_tag, tag_normal) > 0.2 * horizontal_m
        candidate = (
            facing
            & (horizontal_m <= ATTENTION_RANGE_M)
            & (np.abs(to_tag[..., 1]) < CEILING_HEIGHT_M)
            & (np.abs(bearing) < math.pi / 2)
        )
        nearest = np.argmin(np.where(candidate, horizontal_m, np.inf), axis=1)
        rows = np.arange(stop - start)
        has_tag = candidate[rows, nearest] & attentive[start:stop]
        target_rad[start:stop] = np.where(
            has_tag,
            np.clip(bearing[rows, nearest], -MAX_LOOK_RAD, MAX_LOOK_RAD),
            swing_rad[start:stop],
        )
    return gaussian_smooth(target_rad, LOOK_SMOOTHING_S * rate_hz)


def route(
    building: Building,
    length_m: float,
    rng: np.random.Generator,
    *,
    max_floor_changes: int | None = None,
) -> FloatArray:
    """(P, 3) floor-level vertices of a walk ≥ ``length_m`` long, from node 0.

    At each junction the walker takes the least-walked corridor (random among ties), never turning
    back unless it must: corridors get covered, then walked again (loop closures). With stairs,
    the walker stays on a floor for ``min(length_m / 2, that floor's corridors)`` and then takes
    the shortest way to the stairs and changes floor, so even a short walk sees both floors (at
    most ``max_floor_changes`` times; then it stays where it is).
    """
    num_nodes = building.node_xyz_m.shape[0]
    edge_length_m = np.array(
        [np.linalg.norm(np.diff(p, axis=0), axis=1).sum() for p in building.edge_polylines_m]
    )
    ends = building.edge_nodes
    is_stairs = building.node_xyz_m[ends[:, 0], 1] != building.node_xyz_m[ends[:, 1], 1]
    incident: list[list[int]] = [[] for _ in range(num_nodes)]
    for e, (a, b) in enumerate(ends):
        incident[int(a)].append(e)
        incident[int(b)].append(e)
    stair_nodes = sorted({int(v) for v in ends[is_stairs].ravel()})
    to_stairs_m = _graph_distances(
        ends[~is_stairs], edge_length_m[~is_stairs], num_nodes, stair_nodes
    )
    floor_tour_m = min(
        length_m / 2, float(edge_length_m[~is_stairs].sum()) / max(1, len(building.floor_heights_m))
    )
    times_walked = np.zeros(len(edge_length_m), dtype=np.int64)

    def other_end(e: int, node: int) -> int:
        a, b = int(ends[e, 0]), int(ends[e, 1])
        return b if node == a else a

    pieces = [building.node_xyz_m[:1]]
    at, came_by, walked_m, on_floor_m = 0, -1, 0.0, 0.0
    changes_left = math.inf if max_floor_changes is None else max_floor_changes
    while walked_m < length_m:
        stairs_here = [e for e in incident[at] if is_stairs[e]]
        change = stair_nodes and on_floor_m >= floor_tour_m and changes_left > 0
        if change and stairs_here:
            e = stairs_here[0]
            on_floor_m = 0.0
            changes_left -= 1
        elif change:  # head for the stairs
            flat = [e for e in incident[at] if not is_stairs[e]]
            e = min(flat, key=lambda e: edge_length_m[e] + to_stairs_m[other_end(e, at)])
        else:
            flat = [e for e in incident[at] if not is_stairs[e]] or incident[at]
            options = [e for e in flat if e != came_by] or flat
            fewest = min(int(times_walked[e]) for e in options)
            least = [e for e in options if times_walked[e] == fewest]
            e = least[int(rng.integers(len(least)))]
        polyline = building.edge_polylines_m[e]
        if at != int(ends[e, 0]):
            polyline = polyline[::-1]
        pieces.append(polyline[1:])
        walked_m += float(edge_length_m[e])
        on_floor_m += float(edge_length_m[e]) if not is_stairs[e] else 0.0
        times_walked[e] += 1
        at, came_by = other_end(e, at), e
    return np.concatenate(pieces)


def _graph_distances(
    edge_nodes: IntArray, edge_length_m: FloatArray, num_nodes: int, sources: list[int]
) -> FloatArray:
    """(K,) walking distance from each node to the nearest of ``sources``, m (Dijkstra)."""
    neighbours: list[list[tuple[int, float]]] = [[] for _ in range(num_nodes)]
    for (a, b), length in zip(edge_nodes.tolist(), edge_length_m.tolist(), strict=True):
        neighbours[a].append((b, length))
        neighbours[b].append((a, length))
    distance_m = np.full(num_nodes, np.inf)
    queue = [(0.0, s) for s in sources]
    heapq.heapify(queue)
    while queue:
        d, node = heapq.heappop(queue)
        if d >= distance_m[node]:
            continue
        distance_m[node] = d
        for other, length in neighbours[node]:
            if d + length < distance_m[other]:
                heapq.heappush(queue, (d + length, other))
    return distance_m
