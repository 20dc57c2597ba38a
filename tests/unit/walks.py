"""Walks for the navigation tests: polylines of positions as a phone would record them."""

from __future__ import annotations

import itertools
import math

import numpy as np

#: The phone's height above the floor, m.
PHONE_Y_M = 1.3


def line(a_xz, b_xz, *, step_m: float = 0.3, y_m: float = PHONE_Y_M) -> np.ndarray:
    """Points from a to b (x–z, m) every ``step_m``, at height ``y_m``."""
    a, b = np.asarray(a_xz, dtype=float), np.asarray(b_xz, dtype=float)
    count = max(2, math.ceil(float(np.linalg.norm(b - a)) / step_m) + 1)
    t = np.linspace(0.0, 1.0, count)
    xz = a + t[:, None] * (b - a)
    return np.column_stack([xz[:, 0], np.full(count, y_m), xz[:, 1]])


def walk(*corners, step_m: float = 0.3) -> np.ndarray:
    pieces = [line(a, b, step_m=step_m) for a, b in itertools.pairwise(corners)]
    return np.concatenate([pieces[0], *(p[1:] for p in pieces[1:])])
