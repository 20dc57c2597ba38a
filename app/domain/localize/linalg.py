"""Adjoints and small matrix helpers of the smoother."""

from __future__ import annotations

import math

import numpy as np

from app.domain.frames import FloatArray, skew

# --------------------------------------------------------------------------- small helpers


def adjoints(A_T_B: FloatArray) -> FloatArray:
    """(..., 6, 6) adjoint maps of (..., 4, 4) poses in gtsam's ``[rot, trans]`` order:
    ``A_T_B · Exp(ξ_B) · A_T_B⁻¹ = Exp(Ad · ξ_B)``."""
    R = A_T_B[..., :3, :3]
    out = np.zeros((*A_T_B.shape[:-2], 6, 6))
    out[..., :3, :3] = R
    out[..., 3:, 3:] = R
    out[..., 3:, :3] = skew(A_T_B[..., :3, 3]) @ R
    return out


def adjoint(A_T_B: FloatArray) -> FloatArray:
    return adjoints(A_T_B)


def symmetric(M: FloatArray) -> FloatArray:
    return np.asarray(0.5 * (M + M.T), dtype=np.float64)


def yaw_only(A_T_B: FloatArray) -> FloatArray:
    """``A_T_B`` with its rotation replaced by the nearest rotation about +y (gravity)."""
    R = A_T_B[:3, :3]
    yaw_rad = math.atan2(R[0, 2] - R[2, 0], R[0, 0] + R[2, 2])
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    out = A_T_B.copy()
    out[:3, :3] = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    return out


#: Upper-triangle indices of a 6×6 covariance (21 entries), row by row.
UPPER_6 = np.triu_indices(6)
