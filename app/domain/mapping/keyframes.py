"""Keyframes: which phone poses the factor graph holds, and where the others go afterwards.

    keyframes = select_keyframes(timestamp_s, required=pose_indices, interval_s=2.0)   # (K,)
    world_T_phone = interpolate_poses(raw_world_T_phone, timestamp_s, keyframes, world_T_keyframe)

A pose that no used tag detection hangs on is tied to the map only by the odometry to its
neighbours and by gravity, so the graph does not need it: the odometry between two keyframes is
the composition of the steps between them (exact, from the raw poses), with the variance of a
random walk over the time between them. Keeping at most ``interval_s`` between keyframes leaves
the real sessions' maps as they are with every pose (README, "Keyframes") and cuts the graph to a
third or less.

The poses left out are placed by their odometry correction ``C = world_T_phone_optimized ·
world_T_phone_raw⁻¹``, interpolated linearly in time between the keyframes around them (rotation
along the geodesic, translation linearly): for a random walk pinned at both ends, that is the
mean of the path between them.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from app.domain.frames import FloatArray, se3_inverse, so3_exp, so3_log

IntArray = npt.NDArray[np.int64]


def select_keyframes(
    timestamp_s: FloatArray, *, required: npt.ArrayLike, interval_s: float
) -> IntArray:
    """(K,) sorted indices of the poses the graph holds: the first and the last, every index in
    ``required``, and as few others as keep consecutive keyframes at most ``interval_s`` apart
    (a step longer than that on its own keeps both its ends). ``interval_s`` 0: every pose.

    timestamp_s: (N,) s, non-decreasing. required: indices in [0, N).
    """
    n = int(timestamp_s.shape[0])
    if n == 0:
        return np.empty(0, dtype=np.int64)
    if interval_s <= 0:
        return np.arange(n, dtype=np.int64)
    keep = np.zeros(n, dtype=bool)
    keep[[0, n - 1]] = True
    keep[np.asarray(required, dtype=np.int64)] = True
    times = timestamp_s.tolist()
    last_s = times[0]
    for i in range(1, n - 1):
        if keep[i] or times[i + 1] - last_s > interval_s:
            keep[i] = True
            last_s = times[i]
    return np.flatnonzero(keep).astype(np.int64)


def keyframe_spans(keyframes: IntArray, n: int) -> IntArray:
    """(n,) for each of the n poses, the graph's odometry factor that spans it or starts at it:
    ``k`` with ``keyframes[k] ≤ pose ≤ keyframes[k + 1]`` (the last pose: the last factor).
    ``keyframes``: (K,) sorted, K ≥ 2, starting at 0."""
    after = np.searchsorted(keyframes, np.arange(n), side="right") - 1
    return np.asarray(np.minimum(after, keyframes.shape[0] - 2), dtype=np.int64)


def interpolate_poses(
    raw_world_T_phone: FloatArray,
    timestamp_s: FloatArray,
    keyframes: IntArray,
    world_T_keyframe: FloatArray,
) -> FloatArray:
    """(N, 4, 4) every pose of the map: the keyframes' optimized poses, and the others by their
    interpolated odometry correction (see the module docstring).

    raw_world_T_phone: (N, 4, 4) the session's odometry. timestamp_s: (N,) s. keyframes: (K,)
    sorted, starting at 0 and ending at N − 1. world_T_keyframe: (K, 4, 4) optimized.
    """
    n = raw_world_T_phone.shape[0]
    if keyframes.shape[0] == n:
        return np.array(world_T_keyframe, dtype=np.float64)
    correction = world_T_keyframe @ se3_inverse(raw_world_T_phone[keyframes])  # (K, 4, 4)
    segment = keyframe_spans(keyframes, n)
    a, b = keyframes[segment], keyframes[segment + 1]
    span_s = timestamp_s[b] - timestamp_s[a]
    by_index = (np.arange(n) - a) / (b - a)
    fraction = np.where(
        span_s > 0, (timestamp_s - timestamp_s[a]) / np.where(span_s > 0, span_s, 1.0), by_index
    )
    f = fraction[:, None]
    start_R, end_R = correction[segment, :3, :3], correction[segment + 1, :3, :3]
    rotation = start_R @ so3_exp(f * so3_log(np.swapaxes(start_R, -1, -2) @ end_R))
    translation = (1.0 - f) * correction[segment, :3, 3] + f * correction[segment + 1, :3, 3]
    interpolated = np.tile(np.eye(4), (n, 1, 1))
    interpolated[:, :3, :3] = rotation
    interpolated[:, :3, 3] = translation
    world_T_phone = interpolated @ raw_world_T_phone
    world_T_phone[keyframes] = world_T_keyframe  # exactly, not through the correction
    return np.asarray(world_T_phone, dtype=np.float64)
