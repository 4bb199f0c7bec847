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
    ratio to a baseline). Separate cases that every series labels alike (a suite measured by two
    methods) are joined by a thin line and named once, beside their rightmost point."""
    labels = labels or {}
    cases = list(labels.get(next(iter(series), ""), ()))
    shared = not lines and len(series) > 1 and all(list(labels.get(n, ())) == cases for n in series)
    fig, ax = plt.subplots(figsize=(7.2, 5.0) if shared and len(cases) > 8 else (6.4, 3.6), layout="constrained")
    for name, points in series.items():
        xy = np.asarray(points, float).reshape(-1, 2)
        ax.plot(xy[:, 0], xy[:, 1], marker="o", label=name, linewidth=1.2 if lines else 0, zorder=3)
        for (x, y), text in zip(xy, () if shared else labels.get(name, ()), strict=False):
            ax.annotate(text, (x, y), textcoords="offset points", xytext=(4, 4), fontsize=8)
    if shared:
        xy = np.stack([np.asarray(p, float).reshape(-1, 2) for p in series.values()], 1)  # (cases, series, 2)
        named = []
        for case, text in zip(xy, cases, strict=False):
            ax.plot(case[:, 0], case[:, 1], color="0.7", linewidth=0.8, zorder=2)
            x, y = case[case[:, 0].argmax()]
            named.append(ax.annotate(text, (x, y), textcoords="offset points", xytext=(5, -3), fontsize=7))
    ax.set_xscale("log")
    # Ticks at 1, 2 and 5 of each decade, the others unlabelled: every minor tick labelled overlaps.
    ax.xaxis.set_major_locator(matplotlib.ticker.LogLocator(subs=(1.0, 2.0, 5.0), numticks=30))
    ax.xaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
    ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    _label(fig, ax, title, note)
    ax.set_ylim(bottom=0)
    if reference is not None:
        ax.axhline(reference, color="0.4", linestyle="--", linewidth=0.8)
    ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), frameon=False)
    ax.grid(alpha=0.3, which="both")
    if shared:
        _spread(fig, named)
    return _save(fig, path)


def _spread(fig: plt.Figure, texts: list[matplotlib.text.Annotation]) -> None:
    """Move overlapping point labels apart: from the top down, each below the labels already placed
    that it overlaps (a greedy pass in display space). adjustText does this and more; these lines
    spare the service's image a dependency that only the docs' charts would use."""
    fig.canvas.draw()  # the constrained layout places the axes: the boxes are final from here
    renderer, placed = fig.canvas.get_renderer(), []
    for text in sorted(texts, key=lambda t: -t.get_window_extent(renderer).y1):
        for _ in range(len(texts)):
            box = text.get_window_extent(renderer)
            hit = next((b for b in placed if box.overlaps(b)), None)
            if hit is None:
                break
            dx, dy = text.get_position()  # offset points
            text.set_position((dx, dy - (box.y1 - hit.y0 + 1.0) * 72.0 / fig.dpi))
        placed.append(text.get_window_extent(renderer))
