"""docs/benchmarks.md from the committed results in docs/results/: one section per JSON file, in
file-name order, with its device, command and date, and a chart where the file asks for one.

A result file: {"title", "device", "date", "command", "about", "columns", "rows"[, "chart"]};
"chart" is {"kind": "bar", "groups", "series", "mean", "err", "ylabel"} or {"kind": "xy", "series":
{name: [[x, y], ...]}, "labels": {name: [text, ...]}, "xlabel", "ylabel"[, "lines": false (points
alone), "reference": y (a dashed level)]}. Then one section per
device from docs/results/speed/: the files `inhand-tracker bench speed --json` writes.
"""

from __future__ import annotations

import json
from pathlib import Path

from .plots import bar_chart, xy_chart

__all__ = ["SPEED_COLUMNS", "render", "speed_rows"]

SPEED_COLUMNS = [
    "W", "G", "substeps", "solver (iterations / line search[, tolerances])", "tracker median ms", "tracker p99 ms",
    "physics median ms", "physics p99 ms", "M world-substeps/s", "30 Hz (p99)", "memory/world",
]  # fmt: skip
_SPEED_ABOUT = (
    "The whole tracker frame (frame in, estimate out) against the physics alone, replaying the bundled"
    " pick and place (the hand in motion); each of G sessions tracks with K = W / G worlds. World-substeps"
    " per second: W x substeps over the tracker's median. Real time: a p99 within a 30 Hz frame (33.3 ms)."
)


def _number(x: float) -> str:
    """1e-4 rather than 0.0001 or 1e-04: as the settings are written."""
    return f"{x:.0e}".replace("e-0", "e-") if x < 1e-3 else f"{x:g}"


def _solver(r: dict) -> str:
    budget = f"{r['iterations']} / {r['ls_iterations']}"
    if "tolerance" in r:  # files written before the tolerances were settings of `bench speed` lack them
        budget += f", tolerances {_number(r['tolerance'])} / {_number(r['ls_tolerance'])}"
    return f"{r['solver']} ({budget})"


def speed_rows(results: list[dict]) -> list[list]:
    """One row per `bench speed` result under :data:`SPEED_COLUMNS`."""
    return [
        [
            r["worlds"], r["groups"], r["substeps"], _solver(r),
            f"{r['tracker_median_ms']:.2f}", f"{r['tracker_p99_ms']:.2f}", f"{r['physics_median_ms']:.2f}",
            f"{r['physics_p99_ms']:.2f}", f"{r['world_substeps_per_s'] / 1e6:.2f}", "yes" if r["real_time"] else "no",
            f"{r['bytes_per_world'] / 1024:.0f} KiB",
        ]
        for r in results
    ]  # fmt: skip


_HEAD = """# Benchmarks

The current figure of each benchmark, with its device, command and date. This page is generated
from the JSON files in `docs/results/` by `inhand-tracker bench publish`; to add a figure, commit
its result file and run that command. ADD is the mean distance between the object's surface
points at the estimated and the true pose. GPU runs are not bit-reproducible (contact forces are
summed with float atomics): a paper-suite run moves about 3 mm between identical runs, so
settings are compared with paired runs and `--repeats`, with standard errors.
"""

_TAIL = """## Reproduce

- Accuracy: `inhand-tracker bench accuracy --suite {smoke,paper,reality-gap,cross-engine}[-shadow]
  (or manipulate) --noise low,med,high --methods OLP,EYE,WRS,REPS,PBO [--repeats N] [--set NAME=VALUE]
  [--short] [--save-frames] [--robot-overlay FILE]` writes `results.json`, `report.md`, charts and
  (with `--save-frames`) each frame's error, covariance and cost to `bench-results/accuracy-SUITE/`;
  the README describes the suites' truths. `--short` runs a suite's first object and two kinds of
  10 s tracks, as CI does.
- Calibration: `inhand-tracker bench calibration --suite SUITE` records the suite's calibration
  recording in its truth and writes the tracker's fitted servos as an overlay for `--robot-overlay`.
- Speed: `inhand-tracker bench speed --worlds 40,1024,4096,8192 --groups 1 [--substeps 4,6,8]
  [--caps default,4x4] --json > docs/results/speed/DEVICE.json`, one file per device.
- The physics alone: `inhand-tracker bench sim --worlds 40,1024,4096 --json`.
- The service under load: `inhand-tracker bench load --sessions 4 --worlds 40 --rate 30 --seconds 10`
  (robots streaming through real clients to a service embedded on loopback).
- Memory over populations built and dropped: `inhand-tracker bench rebuilds --cycles 1000 --json`.
- The cost's ranking: `inhand-tracker bench cost-ranking --suite SUITE [--short] --method PBO --worlds 40`.
"""


def _cell(value) -> str:
    return "-" if value is None else str(value)


def _chart(path: Path, title: str, chart: dict, note: str) -> Path:
    if chart["kind"] == "xy":
        return xy_chart(
            path, title, chart["series"], chart["xlabel"], chart["ylabel"], chart.get("labels"), note,
            lines=chart.get("lines", True), reference=chart.get("reference"),
        )  # fmt: skip
    return bar_chart(
        path, title, chart["groups"], chart["series"], chart["mean"], chart.get("err"), chart["ylabel"], note
    )


_PAGES = {"hands": "Benchmarks on other hands", "settings": "Benchmarks of the tracker's settings"}
"""Pages of their own beside the main one, by the name a result file gives as its ``page``."""


def render(results: Path, out: Path) -> Path:
    """Write ``out`` (the page) and its charts beside the results; returns the page's path. Result
    files named ``*-tracks.json`` (per-track detail) go to a page of their own beside it,
    ``out``'s name with ``-tracks``, and those that name a ``page`` (:data:`_PAGES`) to ``out``'s
    name with ``-PAGE``; the main page links them."""
    files = sorted(results.glob("*.json"))
    tracks = [p for p in files if p.stem.endswith("-tracks")]
    paged = {p: json.loads(p.read_text()).get("page") for p in files if p not in tracks}
    detail = out.with_name(f"{out.stem}-tracks.md")
    lines = [_HEAD]
    for path in (p for p in files if p not in tracks and not paged.get(p)):
        lines += _section(path, results, out)
    for name, title in _PAGES.items():
        own = [p for p, page in paged.items() if page == name]
        if not own:
            continue
        page_path = out.with_name(f"{out.stem}-{name}.md")
        page = [f"# {title}", "", f"A part of [{out.name}]({out.name}), generated with it.", ""]
        for path in own:
            page += _section(path, results, page_path)
        page_path.write_text("\n".join(page))
        lines += [f"{title}: [{page_path.name}]({page_path.name}).", ""]
    for path in sorted((results / "speed").glob("*.json")):
        r = json.loads(path.read_text())
        lines += [f"## Speed: {r['device']}", "", f"{r['date']}: `{r['command']}`", "", _SPEED_ABOUT, ""]
        lines += ["| " + " | ".join(SPEED_COLUMNS) + " |", "|" + "---|" * len(SPEED_COLUMNS)]
        lines += ["| " + " | ".join(map(str, row)) + " |" for row in speed_rows(r["results"])]
        lines.append("")
    if tracks:
        lines += [f"Per-track figures of the accuracy suites: [{detail.name}]({detail.name}).", ""]
        page = [
            "# Benchmarks per track",
            "",
            f"The per-track detail of [{out.name}]({out.name}), generated with it.",
            "",
        ]
        for path in tracks:
            page += _section(path, results, detail)
        detail.write_text("\n".join(page))
    lines.append(_TAIL)
    out.write_text("\n".join(lines))
    return out


def _section(path: Path, results: Path, page: Path) -> list[str]:
    """One result file's section: its title, provenance, what it shows, its table and chart."""
    r = json.loads(path.read_text())
    lines = [f"## {r['title']}", "", f"{r['device']}, {r['date']}: `{r['command']}`", "", r["about"], ""]
    lines += ["| " + " | ".join(r["columns"]) + " |", "|" + "---|" * len(r["columns"])]
    lines += ["| " + " | ".join(_cell(v) for v in row) + " |" for row in r["rows"]]
    if chart := r.get("chart"):
        note = "; ".join(x for x in (f"{r['device']}, {r['date']}", chart.get("note", "")) if x)
        png = _chart(results / f"{path.stem}.png", r["title"], chart, note)
        lines += ["", f"![{r['title']}]({png.relative_to(page.parent).as_posix()})"]
    return [*lines, ""]
