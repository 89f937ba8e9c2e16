"""Figures of the multi-seed suites (matplotlib, Agg backend, PNG).

* :func:`plot_learning_curves` -- like Fig. 1/3/5: per method, the moving average of episode
  returns against environment steps, mean over seeds with a 95% bootstrap band.
* :func:`plot_td_traces` -- like Fig. 2: (a) mean |TD error| of the training batches and
  (b) the mean H2 sampling weight p (DER methods), against steps, mean over seeds with a band.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from der_ros.experiments.aggregate import evaluation_curve, iqm_band  # noqa: E402
from der_ros.experiments.stats import bootstrap_band, curve_on_grid  # noqa: E402
from der_ros.experiments.suite import RunResult  # noqa: E402

__all__ = ["plot_learning_curves", "plot_td_traces", "plot_eval_curves", "metric_on_grid", "save_figure"]


def save_figure(fig: plt.Figure, path: str | Path, dpi: int = 120) -> Path:
    """Lay out, write (creating the folder) and close ``fig``; returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def _grid(results: Mapping[str, Sequence[RunResult]], n_points: int) -> np.ndarray:
    total = max((int(r.summary.get("steps", 0)) for runs in results.values() for r in runs), default=1)
    return np.linspace(0, total, n_points)


def plot_learning_curves(
    results: Mapping[str, Sequence[RunResult]],
    labels: Mapping[str, str],
    path: str | Path | None,
    window: int = 20,
    title: str = "",
    n_points: int = 200,
    ax: plt.Axes | None = None,
) -> Path | None:
    """Learning curves (mean of ``window``-episode moving averages over seeds, 95% CI band)."""
    own = ax is None
    if own:
        fig, ax = plt.subplots(figsize=(7, 4.2))
    grid = _grid(results, n_points)
    for i, (name, runs) in enumerate(results.items()):
        if not runs:
            continue
        color = f"C{i % 10}"
        curves = np.stack([curve_on_grid(r.episode_steps, r.returns, grid, window) for r in runs])
        mean, lo, hi = bootstrap_band(curves)
        ax.plot(grid, mean, label=f"{labels.get(name, name)} (n={len(runs)})", color=color)
        ax.fill_between(grid, lo, hi, color=color, alpha=0.2, linewidth=0)
    ax.set_xlabel("environment steps")
    ax.set_ylabel(f"return (moving average of {window} episodes)")
    if title:
        ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    if own:
        if path is None:
            raise ValueError("plot_learning_curves needs a path when it makes its own figure")
        return save_figure(fig, path)
    return None


def metric_on_grid(run: RunResult, name: str, grid: np.ndarray, valid_if_positive: str | None = None) -> np.ndarray:
    """A logged metric of one run, linearly interpolated on ``grid`` (NaN outside its range).

    ``valid_if_positive``: another metric logged at the same steps; points where it is <= 0 are
    dropped first (e.g. the H2 weight, logged as 0 while ``replay/h2_size`` is 0).
    """
    if name not in run.metrics:
        return np.full(len(grid), np.nan)
    steps, values = run.metrics[name]
    if valid_if_positive is not None and valid_if_positive in run.metrics:
        ref_steps, ref_values = run.metrics[valid_if_positive]
        ok_steps = set(ref_steps[ref_values > 0].tolist())
        keep = np.fromiter((int(s) in ok_steps for s in steps), dtype=bool, count=steps.size)
        steps, values = steps[keep], values[keep]
    if steps.size == 0:
        return np.full(len(grid), np.nan)
    out = np.interp(grid, steps.astype(np.float64), values)
    out[(grid < steps[0]) | (grid > steps[-1])] = np.nan
    return out


def plot_td_traces(
    results: Mapping[str, Sequence[RunResult]],
    labels: Mapping[str, str],
    path: str | Path,
    title: str = "",
    n_points: int = 200,
) -> Path:
    """Fig. 2 style: (a) mean |TD error| per method, (b) mean H2 weight p of the DER methods."""
    fig, (ax_td, ax_w) = plt.subplots(1, 2, figsize=(11, 4.2))
    grid = _grid(results, n_points)
    any_weight = False
    for i, (name, runs) in enumerate(results.items()):
        if not runs:
            continue
        label, color = labels.get(name, name), f"C{i % 10}"
        for ax, metric in ((ax_td, "losses/abs_td_error"), (ax_w, "replay/h2_weight_mean")):
            # the H2 weight is undefined (logged as 0) while H2 is empty
            valid = "replay/h2_size" if metric == "replay/h2_weight_mean" else None
            values = np.stack([metric_on_grid(r, metric, grid, valid) for r in runs])
            if not np.isfinite(values).any():
                continue
            any_weight |= ax is ax_w
            mean, lo, hi = bootstrap_band(values)
            ax.plot(grid, mean, label=label, color=color)
            ax.fill_between(grid, lo, hi, color=color, alpha=0.2, linewidth=0)
    ax_td.set_title("(a) mean |TD error| of training batches")
    ax_td.set_xlabel("environment steps")
    ax_td.set_ylabel("|δ|")
    ax_td.grid(alpha=0.3)
    ax_td.legend(fontsize=8)
    ax_w.set_title("(b) mean H2 sampling weight p (eq. 3)")
    ax_w.set_xlabel("environment steps")
    ax_w.set_ylabel("p (log scale)")
    ax_w.set_yscale("log")  # p = e^|delta| spans many decades; the baseline is 1
    ax_w.grid(alpha=0.3)
    if any_weight:
        ax_w.legend(fontsize=8)
    else:
        ax_w.text(0.5, 0.5, "no DER runs", ha="center", va="center", transform=ax_w.transAxes)
    if title:
        fig.suptitle(title)
    return save_figure(fig, path)


#: evaluation metric -> axis label
EVAL_METRIC_LABELS = {
    "success": "greedy success rate",
    "collision": "greedy caused-collision rate",
    "time_limit": "greedy time-limit rate",
    "mean_return": "greedy mean return",
}


def plot_eval_curves(
    results: Mapping[str, Sequence[RunResult]],
    labels: Mapping[str, str],
    path: str | Path,
    metrics: Sequence[str] = ("success", "collision"),
    baselines: Mapping[str, Mapping[str, float]] | None = None,
    title: str = "",
    training_window: int | None = 20,
) -> Path:
    """Evaluation curves: per metric, the IQM over seeds of the periodic greedy evaluations against
    training steps with a 95% bootstrap band; baselines as dashed lines; optionally a last panel with
    the training-episode curves of :func:`plot_learning_curves` (the paper's figures)."""
    panels = len(metrics) + (1 if training_window else 0)
    fig, axes = plt.subplots(1, panels, figsize=(5.2 * panels, 4.2), squeeze=False)
    for k, metric in enumerate(metrics):
        ax = axes[0][k]
        for i, (name, runs) in enumerate(results.items()):
            curves = [evaluation_curve(r.spec.run_dir) for r in runs]
            curves = [c for c in curves if c["step"].size]
            if not curves:
                continue
            steps = np.unique(np.concatenate([c["step"] for c in curves]))
            table = np.full((len(curves), steps.size), np.nan)
            for row, c in enumerate(curves):
                table[row, np.searchsorted(steps, c["step"])] = c[metric]
            point, lo, hi = iqm_band(table)
            color = f"C{i % 10}"
            ax.plot(steps, point, marker=".", color=color, label=f"{labels.get(name, name)} (n={len(curves)})")
            ax.fill_between(steps, lo, hi, color=color, alpha=0.2, linewidth=0)
        for j, (bname, values) in enumerate((baselines or {}).items()):
            if metric in values and np.isfinite(values[metric]):
                ax.axhline(values[metric], color="0.3", linestyle=("--", ":", "-.", (0, (5, 1)), (0, (1, 3)))[j % 5],
                           linewidth=1, label=f"baseline: {bname}")  # fmt: skip
        ax.set_xlabel("environment steps")
        ax.set_ylabel(EVAL_METRIC_LABELS.get(metric, metric) + " (IQM, 95% CI)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    if training_window:
        plot_learning_curves(results, labels, None, window=training_window, ax=axes[0][-1],
                             title="training episodes (the paper's figures)")  # fmt: skip
    if title:
        fig.suptitle(title)
    return save_figure(fig, path)
