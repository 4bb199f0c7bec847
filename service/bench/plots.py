"""The benchmarks' charts, drawn with matplotlib (headless: the Agg backend, PNG files)."""

from __future__ import annotations

import textwrap
from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # no display on a GPU box or in CI

import matplotlib.pyplot as plt
import matplotlib.ticker
import numpy as np

__all__ = ["bar_chart", "line_chart", "xy_chart"]


def _label(fig: plt.Figure, ax: plt.Axes, title: str, note: str) -> None:
    """The title, wrapped so a long one is not clipped, and below the axes a note of what was run
    and what the marks are (K, device, runs; what a bar and a whisker stand for)."""
    inches = fig.get_figwidth()  # about 8 title and 15 note characters fit an inch
    ax.set_title(textwrap.fill(title, int(8 * inches)))
    if note:
        fig.supxlabel(textwrap.fill(note, int(15 * inches)), fontsize=7, color="0.3")


def _save(fig: plt.Figure, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def bar_chart(
    path: str | Path,
    title: str,
    groups: Sequence[str],
    series: Sequence[str],
    mean: np.ndarray,
    std: np.ndarray | None = None,
    ylabel: str = "ADD [mm]",
    note: str = "",
) -> Path:
    """Grouped bars: ``mean`` (len(groups), len(series)) with error bars ``std``; NaN bars are left
    out. ``note``: what was run and what the bars and whiskers are, under the chart."""
    mean = np.asarray(mean, float)
    std = np.zeros_like(mean) if std is None else np.asarray(std, float)
    fig, ax = plt.subplots(
        figsize=(max(5.2, 0.9 * len(groups) * max(1, len(series)) / 3 + 2.2), 3.6), layout="constrained"
    )
    width = 0.8 / max(len(series), 1)
    x = np.arange(len(groups))
    for j, name in enumerate(series):
        shown = np.isfinite(mean[:, j])
        ax.bar(x[shown] + (j - (len(series) - 1) / 2) * width, mean[shown, j], width, yerr=std[shown, j],
               capsize=3, label=name)  # fmt: skip
    ax.set_xticks(x, groups)
    ax.set_ylabel(ylabel)
    _label(fig, ax, title, note)
    ax.set_ylim(bottom=0)
    ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), frameon=False)
    ax.grid(axis="y", alpha=0.3)
    return _save(fig, path)


def line_chart(
    path: str | Path,
    title: str,
    series: dict[str, np.ndarray],
    x_step: float = 1.0,
    xlabel: str = "time [s]",
    ylabel: str = "ADD [mm]",
    note: str = "",
) -> Path:
    """One line per series over x = index * ``x_step``; ``note`` under the chart."""
    fig, ax = plt.subplots(figsize=(7.2, 3.6), layout="constrained")
    for name, values in series.items():
        values = np.asarray(values, float)
        ax.plot(np.arange(values.size) * x_step, values, label=name, linewidth=1.2)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    _label(fig, ax, title, note)
    ax.set_ylim(bottom=0)
    ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), frameon=False)
    ax.grid(alpha=0.3)
    return _save(fig, path)


def xy_chart(
    path: str | Path,
    title: str,
    series: dict[str, Sequence[Sequence[float]]],
    xlabel: str,
    ylabel: str = "ADD [mm]",
    labels: dict[str, Sequence[str]] | None = None,
    note: str = "",
    lines: bool = True,
    reference: float | None = None,
) -> Path:
    """One marked line per series through its (x, y) points (points alone without ``lines``, where
    the points are separate cases), each point annotated with its label (e.g. K); x on a log scale,
    as frame times and world counts span decades; ``reference`` draws a dashed level (e.g. 1 for a
    ratio to a baseline)."""
    fig, ax = plt.subplots(figsize=(6.4, 3.6), layout="constrained")
    for name, points in series.items():
        xy = np.asarray(points, float).reshape(-1, 2)
        ax.plot(xy[:, 0], xy[:, 1], marker="o", label=name, linewidth=1.2 if lines else 0)
        for (x, y), text in zip(xy, (labels or {}).get(name, ()), strict=False):
            ax.annotate(text, (x, y), textcoords="offset points", xytext=(4, 4), fontsize=8)
    ax.set_xscale("log")
    ax.xaxis.set_major_formatter(matplotlib.ticker.ScalarFormatter())
    ax.xaxis.set_minor_formatter(matplotlib.ticker.ScalarFormatter())
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    _label(fig, ax, title, note)
    ax.set_ylim(bottom=0)
    if reference is not None:
        ax.axhline(reference, color="0.4", linestyle="--", linewidth=0.8)
    ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), frameon=False)
    ax.grid(alpha=0.3, which="both")
    return _save(fig, path)
