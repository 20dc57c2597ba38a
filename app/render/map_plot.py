"""Top-down plots of a map (the paper's Fig. 2): one panel per floor, in the horizontal x–z plane.

    render_map_png(result, session, ground_truth=gt, path="map.png")

Each panel shows the raw odometry and the optimized trajectory, the pre-optimized tags (first
observation) and the optimized ones with 2σ position ellipses, and, when given, ground-truth tags
aligned to the optimized map by a best-fit rigid transform. Uses matplotlib's Agg backend. Names
from users (the map's, the points of interest's) are drawn literally (``parse_math=False``: a
"$" is a dollar sign, never mathtext that could fail to parse).
"""

from __future__ import annotations

import io
import warnings
from collections.abc import Mapping
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.axes import Axes
from matplotlib.patches import Ellipse

from app.domain.evaluation.metrics import umeyama_rigid
from app.domain.frames import FloatArray
from app.domain.mapping.map_result import MapResult
from app.domain.mapping.uncertainty import horizontal_position_ellipse
from app.domain.navigation.floors import assign_floors, find_floor_levels
from app.domain.upload.session import Session

RAW_COLOUR = "#9e9e9e"
OPTIMIZED_COLOUR = "#1565c0"
PRE_TAG_COLOUR = "#ef6c00"
TAG_COLOUR = "#2e7d32"
TRUTH_COLOUR = "#c62828"


def render_map_png(
    result: MapResult,
    session: Session | None = None,
    *,
    ground_truth: Mapping[int, FloatArray] | None = None,
    path: str | Path | None = None,
    title: str | None = None,
) -> bytes:
    """Draw the map; returns the PNG bytes and writes them to ``path`` when given."""
    heights_m = result.world_T_phone[:, 1, 3]
    levels_m = find_floor_levels(heights_m)
    floor_of_pose = assign_floors(heights_m, levels_m)
    floor_of_tag = assign_floors(result.world_T_tag[:, 1, 3], levels_m)
    aligned_truth = _aligned_ground_truth(result, ground_truth)

    panels = max(1, len(levels_m))
    figure, axes = plt.subplots(1, panels, figsize=(7.5 * panels, 7.0), squeeze=False)
    for floor, axis in enumerate(axes[0]):
        on_floor = floor_of_pose == floor
        if session is not None:
            raw_xz = session.world_T_phone[:, [0, 2], 3]
            axis.plot(*_masked(raw_xz, on_floor).T, color=RAW_COLOUR, lw=1, label="raw odometry")
        opt_xz = result.world_T_phone[:, [0, 2], 3]
        axis.plot(*_masked(opt_xz, on_floor).T, color=OPTIMIZED_COLOUR, lw=1.2, label="optimized")
        tags_here = floor_of_tag == floor
        pre_xz = result.world_T_tag_pre[tags_here][:, [0, 2], 3]
        axis.scatter(*pre_xz.T, marker="x", color=PRE_TAG_COLOUR, label="tags, pre-optimized")
        tag_xz = result.world_T_tag[tags_here][:, [0, 2], 3]
        axis.scatter(
            *tag_xz.T, marker="s", s=28, color=TAG_COLOUR, label="tags, optimized (2σ from start)"
        )
        for k in np.flatnonzero(tags_here):
            _draw_position_ellipse(axis, result, int(k))
            x, z = result.world_T_tag[k, [0, 2], 3]
            axis.annotate(
                str(int(result.tag_ids[k])),
                (x, z),
                fontsize=7,
                xytext=(3, 3),
                textcoords="offset points",
            )
        if aligned_truth:
            truth = np.array([T[[0, 2], 3] for T in aligned_truth.values()])
            truth_floor = assign_floors(
                np.array([T[1, 3] for T in aligned_truth.values()]), levels_m
            )
            here = truth[truth_floor == floor]
            axis.scatter(
                *here.T,
                marker="o",
                facecolors="none",
                edgecolors=TRUTH_COLOUR,
                s=60,
                label="tags, ground truth (aligned)",
            )
        for poi_k, name in enumerate(result.poi_names):
            x, y, z = result.world_T_poi[poi_k, :3, 3]
            if assign_floors(np.array([y]), levels_m)[0] == floor:
                axis.scatter([x], [z], marker="*", s=90, color="black")
                axis.annotate(
                    name,
                    (x, z),
                    fontsize=8,
                    xytext=(4, -8),
                    textcoords="offset points",
                    parse_math=False,  # a user's "$" is a dollar sign, not mathtext
                )
        axis.set_aspect("equal", adjustable="datalim")
        axis.set_xlabel("x (m)")
        axis.set_ylabel("z (m)")
        axis.invert_yaxis()  # looking down from +y: x right, z toward the viewer's bottom
        axis.grid(True, lw=0.3)
        level = f" (y ≈ {levels_m[floor]:.1f} m)" if len(levels_m) else ""
        axis.set_title(f"floor {floor}{level}" if panels > 1 else f"top-down{level}")
        axis.legend(loc="best", fontsize=7)
    figure.suptitle(
        title
        or f"{result.map_id}: {len(result.tag_ids)} tags, {result.world_T_phone.shape[0]} poses",
        parse_math=False,  # the map's name is the user's: drawn as written
    )
    buffer = io.BytesIO()
    with warnings.catch_warnings():  # a name in a script the font lacks: boxes, not a failure
        warnings.filterwarnings(
            "ignore", message=r"Glyph \d+ .* missing from font", category=UserWarning
        )
        figure.tight_layout()
        figure.savefig(buffer, format="png", dpi=110)
    plt.close(figure)
    png = buffer.getvalue()
    if path is not None:
        Path(path).write_bytes(png)
    return png


def _masked(xz: FloatArray, mask: np.ndarray) -> FloatArray:
    """Points with NaN where ``mask`` is False, so that lines break between floors."""
    out = xz.copy()
    out[~mask] = np.nan
    return out


def _draw_position_ellipse(axis: Axes, result: MapResult, k: int) -> None:
    ellipse = horizontal_position_ellipse(
        result.world_T_tag[k, :3, :3], result.tag_covariance[k], sigmas=2.0
    )
    if ellipse is None:
        return
    x, z = result.world_T_tag[k, [0, 2], 3]
    axis.add_patch(
        Ellipse(
            (x, z),
            ellipse.width_m,
            ellipse.height_m,
            angle=ellipse.angle_deg,
            fill=False,
            lw=0.8,
            color=TAG_COLOUR,
        )
    )


def _aligned_ground_truth(
    result: MapResult, ground_truth: Mapping[int, FloatArray] | None
) -> dict[int, FloatArray]:
    if not ground_truth:
        return {}
    common = [int(t) for t in result.tag_ids if int(t) in ground_truth]
    if len(common) < 3:
        return {}
    map_xyz = np.array([result.world_T_tag[result.tag_index(t), :3, 3] for t in common])
    truth_xyz = np.array([ground_truth[t][:3, 3] for t in common])
    map_T_truth = umeyama_rigid(truth_xyz, map_xyz)
    return {t: map_T_truth @ ground_truth[t] for t in common}
