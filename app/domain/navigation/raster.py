"""Binary-image operations for the corridor skeleton (``app.domain.navigation.skeleton``), in numpy
only: points along segments, disk dilation, and Zhang–Suen thinning.

    samples = densify(starts_xz, ends_xz, 0.1)      # points no farther apart than 0.1 m
    band = dilate(mask, 3.6)                        # widened by a disk of 3.6 cells
    line = thin(band)                               # one-cell, 8-connected centrelines
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import numpy.typing as npt

from app.domain.frames import FloatArray

BoolArray = npt.NDArray[np.bool_]


def densify(starts: FloatArray, ends: FloatArray, spacing_m: float) -> FloatArray:
    """Points along segments (M, 2) → (M, 2), no two consecutive farther apart than spacing."""
    length = np.linalg.norm(ends - starts, axis=1)
    pieces = np.maximum(1, np.ceil(length / spacing_m).astype(np.int64))
    segment = np.repeat(np.arange(starts.shape[0]), pieces + 1)
    offsets = np.concatenate([[0], np.cumsum(pieces + 1)[:-1]])
    t = (np.arange(segment.shape[0]) - np.repeat(offsets, pieces + 1)) / np.repeat(
        pieces, pieces + 1
    )
    return np.asarray(starts[segment] + (ends - starts)[segment] * t[:, None], dtype=np.float64)


def dilate(mask: BoolArray, radius_px: float) -> BoolArray:
    """``mask`` widened by a disk of ``radius_px`` cells: a row dilation (by running sums) per
    row offset of the disk."""
    r = math.floor(radius_px)
    if r <= 0:
        return mask.copy()
    rows, cols = mask.shape
    padded = np.zeros((rows + 2 * r, cols + 2 * r + 1), dtype=np.int32)
    padded[r : r + rows, r + 1 : r + 1 + cols] = mask
    running = np.cumsum(padded, axis=1)
    by_width: dict[int, BoolArray] = {}
    out = np.zeros((rows, cols), dtype=np.bool_)
    for dy in range(-r, r + 1):
        w = math.floor(math.sqrt(max(radius_px * radius_px - dy * dy, 0.0)))
        if w not in by_width:
            # columns c − w … c + w of the padded row (shifted by r + 1)
            hi = running[:, r + 1 + w : r + 1 + w + cols]
            lo = running[:, r - w : r - w + cols]
            by_width[w] = (hi - lo) > 0
        out |= by_width[w][r + dy : r + dy + rows]
    return out


def thin(mask: BoolArray) -> BoolArray:
    """Zhang–Suen thinning of a binary image to 8-connected one-cell lines (border cells must be
    empty)."""
    img = mask.astype(np.uint8)
    rows_any = np.flatnonzero(mask.any(axis=1))
    cols_any = np.flatnonzero(mask.any(axis=0))
    if rows_any.size == 0:
        return mask.copy()
    r0, r1 = max(rows_any[0] - 1, 0), min(rows_any[-1] + 2, mask.shape[0])
    c0, c1 = max(cols_any[0] - 1, 0), min(cols_any[-1] + 2, mask.shape[1])
    work = img[r0:r1, c0:c1].copy()
    while True:
        changed = False
        for step in (0, 1):
            P = work
            p2, p3, p4 = P[:-2, 1:-1], P[:-2, 2:], P[1:-1, 2:]
            p5, p6, p7 = P[2:, 2:], P[2:, 1:-1], P[2:, :-2]
            p8, p9 = P[1:-1, :-2], P[:-2, :-2]
            ring = (p2, p3, p4, p5, p6, p7, p8, p9, p2)
            count = p2 + p3 + p4 + p5 + p6 + p7 + p8 + p9
            transitions = sum(
                ((a == 0) & (b == 1)).astype(np.uint8) for a, b in itertools.pairwise(ring)
            )
            if step == 0:
                keep_rule = ((p2 * p4 * p6) == 0) & ((p4 * p6 * p8) == 0)
            else:
                keep_rule = ((p2 * p4 * p8) == 0) & ((p2 * p6 * p8) == 0)
            remove = (
                (P[1:-1, 1:-1] == 1) & (count >= 2) & (count <= 6) & (transitions == 1) & keep_rule
            )
            if remove.any():
                work[1:-1, 1:-1][remove] = 0
                changed = True
        if not changed:
            break
    out = np.zeros_like(mask)
    out[r0:r1, c0:c1] = work.astype(np.bool_)
    return out
