"""Plots of a sweep (the paper's Fig. 3 and heat maps), as PNG bytes; matplotlib's Agg backend.

    heatmap_png(space, trials, objective="shift")    # one panel per pair of swept parameters
    shift_vs_gt_png(trials)                          # shift against ground-truth metric, ρ

A heat-map cell is the best (lowest) score of the trials whose two parameters fall in that cell,
over every value of the other parameters: the profile a person tuning by hand would look at. For a
grid the cells are its values; for a sampler, log-spaced bins of the same number per axis.
"""

from __future__ import annotations

import functools
import io
import itertools
import math
import threading
from collections.abc import Callable, Sequence
from typing import ParamSpec, TypeVar

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.colors import LogNorm
from matplotlib.figure import Figure

from app.domain.evaluation.tuning import SearchSpace, Trial, best_trial, shift_gt_correlation

P = ParamSpec("P")
R = TypeVar("R")
#: pyplot's figures and matplotlib's text layout are not thread-safe, and the API renders plots in
#: its thread pool (a page asking for two plots at once made one fail): one plot at a time.
_PLOT_LOCK = threading.Lock()


def _one_at_a_time(render: Callable[P, R]) -> Callable[P, R]:
    @functools.wraps(render)
    def locked(*args: P.args, **kwargs: P.kwargs) -> R:
        with _PLOT_LOCK:
            return render(*args, **kwargs)

    return locked


OBJECTIVE_LABELS = {"shift": "shift metric", "ground_truth": "ground-truth metric"}
SHORT_NAMES = {
    "tag_position_var_m2": "tag position var (m²)",
    "tag_orientation_var_rad2": "tag orientation var (rad²)",
    "odom_linear_var_m2_per_s": "odometry linear var (m²/s)",
    "odom_angular_var_rad2_per_s": "odometry angular var (rad²/s)",
    "gravity_var_rad2": "gravity var (rad²)",
}


@_one_at_a_time
def heatmap_png(space: SearchSpace, trials: Sequence[Trial], *, objective: str) -> bytes:
    """Best score per cell for every pair of swept parameters (a single axis: score vs value)."""
    pairs = list(itertools.combinations(range(len(space.axes)), 2))
    panels = max(1, len(pairs))
    columns = min(panels, 3)
    rows = math.ceil(panels / columns)
    figure, axes_grid = plt.subplots(
        rows, columns, figsize=(4.6 * columns, 4.0 * rows), squeeze=False
    )
    label = OBJECTIVE_LABELS.get(objective, objective)
    if not pairs:
        _score_curve(axes_grid[0][0], space, trials, objective, label)
    for k, (i, j) in enumerate(pairs):
        _pair_panel(axes_grid[k // columns][k % columns], space, trials, objective, i, j, label)
    for k in range(len(pairs), rows * columns):
        axes_grid[k // columns][k % columns].set_visible(False)
    figure.suptitle(f"Best {label} per cell ({len(trials)} trials; ★ best)")
    return _png(figure)


def _edges(low: float, high: float, num: int) -> np.ndarray:
    """``num`` log-spaced bins centred on the grid values."""
    if num == 1:
        return np.array([math.log10(low) - 0.5, math.log10(high) + 0.5])
    centres = np.linspace(math.log10(low), math.log10(high), num)
    half = (centres[1] - centres[0]) / 2
    return np.concatenate([centres - half, [centres[-1] + half]])


def _pair_panel(axes, space, trials, objective, i, j, label) -> None:  # type: ignore[no-untyped-def]
    axis_x, axis_y = space.axes[i], space.axes[j]
    edges_x = _edges(axis_x.low, axis_x.high, max(axis_x.num, 2))
    edges_y = _edges(axis_y.low, axis_y.high, max(axis_y.num, 2))
    cells = np.full((len(edges_y) - 1, len(edges_x) - 1), np.nan)
    for trial in trials:
        score = trial.score(objective)
        if not math.isfinite(score):
            continue
        bin_x = np.searchsorted(edges_x, math.log10(trial.values[axis_x.name]), side="right")
        bin_y = np.searchsorted(edges_y, math.log10(trial.values[axis_y.name]), side="right")
        cx = int(np.clip(bin_x - 1, 0, cells.shape[1] - 1))
        cy = int(np.clip(bin_y - 1, 0, cells.shape[0] - 1))
        if not score >= cells[cy, cx]:  # NaN or lower
            cells[cy, cx] = score
    finite = cells[np.isfinite(cells)]
    norm = LogNorm() if finite.size and finite.min() > 0 and finite.max() > finite.min() else None
    image = axes.pcolormesh(
        edges_x, edges_y, np.ma.masked_invalid(cells), cmap="viridis_r", norm=norm
    )
    axes.figure.colorbar(image, ax=axes, label=label)
    best = best_trial(trials, objective)
    if best is not None:
        axes.plot(
            math.log10(best.values[axis_x.name]),
            math.log10(best.values[axis_y.name]),
            marker="*",
            markersize=16,
            color="#d50000",
            markeredgecolor="white",
        )
    axes.set_xlabel(f"log10 {SHORT_NAMES.get(axis_x.name, axis_x.name)}")
    axes.set_ylabel(f"log10 {SHORT_NAMES.get(axis_y.name, axis_y.name)}")


def _score_curve(axes, space, trials, objective, label) -> None:  # type: ignore[no-untyped-def]
    axis = space.axes[0]
    points = sorted(
        (trial.values[axis.name], trial.score(objective))
        for trial in trials
        if math.isfinite(trial.score(objective))
    )
    if points:
        x, y = zip(*points, strict=True)
        axes.semilogx(x, y, "o-")
    axes.set_xlabel(SHORT_NAMES.get(axis.name, axis.name))
    axes.set_ylabel(label)


@_one_at_a_time
def shift_vs_gt_png(trials: Sequence[Trial], *, gt_metric_pre: float | None = None) -> bytes:
    """Shift metric against ground-truth metric over the converged trials (the paper's Fig. 3),
    with the Spearman correlation, both metrics' choices marked and, when given, the
    pre-optimized map's ground-truth metric as a line."""
    figure, axes = plt.subplots(figsize=(6.0, 4.8))
    if gt_metric_pre is not None and math.isfinite(gt_metric_pre):
        axes.axhline(gt_metric_pre, color="#616161", linestyle="--", label="pre-optimized")
    usable = [
        t for t in trials if t.converged and math.isfinite(t.shift) and math.isfinite(t.gt_metric)
    ]
    if usable:
        axes.scatter(
            [t.shift for t in usable],
            [t.gt_metric for t in usable],
            s=10,
            alpha=0.5,
            color="#1565c0",
            label="trials",
        )
        by_shift = best_trial(usable, "shift")
        by_gt = best_trial(usable, "ground_truth")
        for trial, colour, name in (
            (by_shift, "#d50000", "shift-chosen"),
            (by_gt, "#2e7d32", "ground-truth-chosen"),
        ):
            if trial is not None:
                axes.scatter(
                    [trial.shift], [trial.gt_metric], s=120, marker="*", color=colour, label=name
                )
        axes.set_xscale("log")
        axes.legend(loc="best")
    else:
        axes.text(0.5, 0.5, "no trial has both metrics", ha="center", transform=axes.transAxes)
    rho = shift_gt_correlation(trials)
    axes.set_title(f"Shift vs ground-truth metric ({len(usable)} trials, Spearman ρ = {rho:.2f})")
    axes.set_xlabel("shift metric (lower is better)")
    axes.set_ylabel("ground-truth metric (lower is better)")
    return _png(figure)


def _png(figure: Figure) -> bytes:
    buffer = io.BytesIO()
    figure.tight_layout()
    figure.savefig(buffer, format="png", dpi=90)
    plt.close(figure)
    return buffer.getvalue()
