"""A tag's position uncertainty seen from above: the ellipse of its marginal covariance in the
horizontal x–z plane of the map (y up).

    ellipse = horizontal_position_ellipse(world_R_tag, covariance_rot_trans, sigmas=2.0)
    ellipse.width_m, ellipse.height_m, ellipse.angle_deg     # full axes, m; angle from +x, deg
    ellipse.outline_xz(center_xz, points=24)                 # (24, 2) m, for a plot
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from app.domain.frames import FloatArray


@dataclass(frozen=True, slots=True, kw_only=True)
class HorizontalEllipse:
    """An ellipse in the x–z plane: ``width_m`` along the axis at ``angle_deg`` from +x (towards
    +z), ``height_m`` across it; both full lengths (2 × semi-axis), m."""

    width_m: float
    height_m: float
    angle_deg: float

    def outline_xz(self, center_xz: FloatArray, *, points: int = 24) -> FloatArray:
        """``points`` points of the closed outline around ``center_xz`` (2,), m: (points, 2)."""
        t = np.linspace(0.0, 2.0 * math.pi, points)
        angle = math.radians(self.angle_deg)
        along = np.array([math.cos(angle), math.sin(angle)])
        across = np.array([-math.sin(angle), math.cos(angle)])
        return np.asarray(
            center_xz[None, :]
            + np.outer(np.cos(t), along) * self.width_m / 2
            + np.outer(np.sin(t), across) * self.height_m / 2,
            dtype=np.float64,
        )


def horizontal_position_ellipse(
    world_R_tag: FloatArray, covariance_rot_trans: FloatArray, *, sigmas: float = 2.0
) -> HorizontalEllipse | None:
    """The ``sigmas``-σ ellipse of a tag's position in the map's x–z plane.

    world_R_tag: (3, 3) the tag's orientation in the map frame.
    covariance_rot_trans: (6, 6) marginal covariance in the tag frame, [rotation rad, translation
        m] (gtsam's Pose3 tangent order). None when it has a non-finite entry (not computed).
    """
    if not np.all(np.isfinite(covariance_rot_trans)):
        return None
    position_cov_world = world_R_tag @ covariance_rot_trans[3:, 3:] @ world_R_tag.T
    cov_xz = position_cov_world[np.ix_([0, 2], [0, 2])]
    eigenvalues, eigenvectors = np.linalg.eigh(cov_xz)
    eigenvalues = np.maximum(eigenvalues, 0.0)
    angle_deg = float(np.degrees(np.arctan2(eigenvectors[1, 1], eigenvectors[0, 1])))
    width_m, height_m = (2 * sigmas * np.sqrt(eigenvalues[::-1])).tolist()
    return HorizontalEllipse(width_m=width_m, height_m=height_m, angle_deg=angle_deg)
