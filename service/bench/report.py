"""The accuracy benchmark's outputs: results JSON, a Markdown report and its PNG charts."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from inhand_tracker.service.tracker import METHODS

from .plots import bar_chart, line_chart
from .suites import NOISE_LEVELS

__all__ = ["write_report"]

_STUDY_TITLES = {
    "exploration": "Exploration (parameter and wrench noise x0.25, x1, x4)",
    "worlds": "Worlds per track K",
    "contact": "Contact terms (w4-w6, touch zones w11-w12)",
    "slip": "Slip terms (w7-w10)",
}


def write_report(results: dict, out: str | Path, command: str = "") -> Path:
    """Write ``results.json``, ``report.md`` and the charts into ``out``; returns the report's path."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps(results))
    summary = results["summary"]
    methods = [m for m in METHODS if m in summary]
    noises = [n for n in NOISE_LEVELS if any(n in summary[m] for m in methods)]
    lines = _head(results, command)
    lines += _fig2(results, methods, noises, out)
    lines += _uncertainty(summary, methods, noises)
    lines += _loss(summary, methods)
    if best_world := results.get("summary_best_world"):
        lines += [
            "## ADD of the lowest-cost world",
            "",
            "The same tracks scored on the lowest-cost world's pose (the paper's estimate) instead of"
            " the estimate reported.",
            "",
            *_table(best_world, methods, noises),
            "",
        ]
    lines += _ablations(results["ablations"], out, results)
    lines += _per_trajectory(results, methods, noises, out)
    path = out / "report.md"
    path.write_text("\n".join(line for line in lines if line is not None) + "\n")
    return path


def _head(results: dict, command: str) -> list[str | None]:
    """What was run, on what, with which settings."""
    suite = results["suite"]
    return [
        f"# Accuracy: suite `{suite['name']}`",
        "",
        f"- command: `{command}`" if command else "",
        f"- device: {results['device']}; K = {results['worlds']} worlds per track (OLP: 1); "
        f"{results['substeps']} tracker substeps per frame",
        f"- {len({t['trajectory'] for t in results['tracks']})} trajectories of about {suite['seconds']:g} s at 30 Hz "
        f"({', '.join(suite['kinds'])}; {', '.join(suite['objects'])}); "
        f"ground truth {results['seconds']['ground_truth']:.0f} s, tracking {results['seconds']['tracking']:.0f} s",
        (
            "- truth recorded in MuJoCo C from the robot's MJCF (1 ms step, its own collision detection)"
            if suite.get("engine") == "mujoco"
            else f"- truth recorded in MuJoCo C from `{suite['scene']['path']}` as its authors ship it"
            " (robot mount, actuators, object, contact settings, step and touch sensors)"
            if suite.get("engine") == "scene"
            else f"- truth physics off from the tracker's: {suite['gap']}"
        )
        + f"; sensor noise: {suite['sensors']}",
        f"- tracker settings other than the defaults: {results['tracker']}" if results.get("tracker") else None,
        f"- tracker physics other than the defaults: {results['population']}" if results.get("population") else None,
        "- the tracker's robot has its servos from a calibration on the robot's own recording"
        f" ({', '.join(results['servos'])} per joint; the truth keeps its own)"
        if results.get("servos")
        else None,
        (
            f"- a camera's pose estimates reach the tracker: {seen['schedule']}, with noise"
            f" {seen['vision_sigma'][0] * 1e3:g} mm and {seen['vision_sigma'][1]:g} rad"
            if (seen := results.get("observations", {})).get("schedule", "none") != "none"
            else "- no camera: the tracker sees only what the robot senses (the paper)"
        ),
        "",
    ]


def _fig2(results: dict, methods: list[str], noises: list[str], out: Path) -> list[str]:
    """The paper's Fig. 2: ADD per method and initial noise, as a table and a chart."""
    summary = results["summary"]
    lines = [
        "## ADD per method and initial noise (the paper's Fig. 2)",
        "",
        "Mean over tracks of each track's mean ADD over its frames, its std over tracks, and the max over all"
        " frames [mm]"
        + (
            f"; the suite was run {repeats} times (each its own noisy initial poses and tracker noise), and"
            " each run's mean follows in brackets."
            if (repeats := results.get("repeats", 1)) > 1
            else "."
        ),
        "",
    ]
    lines += _table(summary, methods, noises)
    mean = np.array([[summary[m].get(n, {}).get("mean_mm", np.nan) for m in methods] for n in noises])
    std = np.array([[summary[m].get(n, {}).get("std_mm", 0.0) for m in methods] for n in noises])
    marks = "bars: mean over tracks of each track's mean ADD; whiskers: std over tracks"
    groups = [n.upper() for n in noises]
    bar_chart(
        out / "fig2.png", f"ADD {results['suite']['name']}", groups, methods, mean, std, note=_what_ran(results, marks)
    )
    return [*lines, "", "![ADD per method and noise](fig2.png)", ""]


def _uncertainty(summary: dict, methods: list[str], noises: list[str]) -> list[str]:
    """ADD-S, and how honest the reported uncertainty and the status were."""
    lines = [
        "## ADD-S and the reported uncertainty",
        "",
        "ADD-S (each estimated surface point to the nearest true one, every tenth frame) scores a turned"
        " symmetric object as it looks; coverage is the share of frames whose true pose lies in the"
        " estimate's reported 95 % region (6-dof Mahalanobis bound): 0.95 is honest, lower over-confident;"
        " flagged: of the times the error rose past 20 mm, those on which the status said uncertain,"
        " ambiguous, diverged or recovering within 1 s.",
        "",
        "| method | " + " | ".join(f"{n} ADD-S mm | {n} coverage | {n} flagged" for n in noises) + " |",
        "|---|" + "---|---|---|" * len(noises),
    ]
    for m in methods:
        cells = [
            f"{c['add_s_mean_mm']:.2f} | {c['coverage_95']:.2f} | {c['flagged_within_1s']} of {c['error_onsets']}"
            if "add_s_mean_mm" in (c := summary[m].get(n, {}))
            else "- | - | -"
            for n in noises
        ]  # fmt: skip
        lines.append(f"| {m} | " + " | ".join(cells) + " |")
    return [*lines, ""]


def _loss(summary: dict, methods: list[str]) -> list[str]:
    """On a loss suite: how soon the status said so, and how soon the estimate came back."""
    if not any("flag_after_s" in c for m in methods for c in summary[m].values()):
        return []
    lines = [
        "## Loss and recovery",
        "",
        "The object slips out of the hand mid-carry, unseen: seconds from the loss to the status"
        " saying anything but tracking, and to the estimate back within 10 mm for 0.5 s (mean over"
        " the tracks that got there; how many never did in brackets).",
        "",
        "| method | noise | status says so after s | back within 10 mm after s |",
        "|---|---|---|---|",
    ]
    for m in methods:
        for n, c in summary[m].items():
            if "flag_after_s" in c:
                cells = [
                    ("-" if c[k] is None else f"{c[k]:.2f}") + f" [{c[k.replace('_after_s', '_never')]}]"
                    for k in ("flag_after_s", "back_within_10mm_after_s")
                ]
                lines.append(f"| {m} | {n} | " + " | ".join(cells) + " |")
    return [*lines, ""]


def _what_ran(results: dict, marks: str) -> str:
    """A chart's note: K, the device, the runs and tracks, and what its marks are."""
    tracks = len({(t["trajectory"], t["repeat"]) for t in results["tracks"]})
    runs = results.get("repeats", 1)
    return f"K = {results['worlds']} worlds (OLP: 1), {results['device']}, {runs} run(s), {tracks} track runs; {marks}"


def _ablations(ablations: dict, out: Path, results: dict) -> list[str]:
    """The paper's Fig. 3: a table and a chart per ablation study."""
    lines: list[str] = []
    for study, rows in ablations.items():
        labels = list(rows)
        lines += [
            f"## Ablation: {_STUDY_TITLES.get(study, study)} (PBO, med noise)",
            "",
            "| setting | mean ADD [mm] | std [mm] | tracks |",
            "|---|---|---|---|",
        ]
        lines += [f"| {k} | {_runs(v)} | {v['std_mm']:.2f} | {v['tracks']} |" for k, v in rows.items()]
        bar_chart(
            out / f"ablation_{study}.png",
            study,
            labels,
            ["PBO"],
            np.array([[rows[k]["mean_mm"]] for k in labels]),
            np.array([[rows[k]["std_mm"]] for k in labels]),
            note=_what_ran(results, "bars: mean ADD over tracks; whiskers: std over tracks (PBO, med noise)"),
        )
        lines += ["", f"![{study}](ablation_{study}.png)", ""]
    return lines


def _per_trajectory(results: dict, methods: list[str], noises: list[str], out: Path) -> list[str]:
    """A row and an ADD-over-time chart per trajectory, at medium noise (or the one run)."""
    tracks = [t for t in results["tracks"] if t["study"] == "main"]
    noise = "med" if "med" in noises else noises[0]
    names = sorted({t["trajectory"] for t in tracks})
    lines = [
        f"## Per trajectory ({noise} noise): mean ADD [mm], frames the tracker re-seeded in brackets"
        + (", one entry per run" if results.get("repeats", 1) > 1 else ""),
        "",
        "The open-loop column is how far the tracker's physics, started at the true pose with the true"
        " mass and friction, drifts from the truth (mean / max ADD, mm): the engines' disagreement"
        " about the track's motion; and, after the x, how hard its hand presses against the truth's"
        " (summed touch or fingertip force, simulated over true).",
        "",
        "| trajectory | open loop | " + " | ".join(methods) + " |",
        "|---|---|" + "---|" * len(methods),
    ]
    for name in names:
        runs: dict[str, list[dict]] = {}
        for t in tracks:
            if t["trajectory"] == name and t["noise"] == noise:
                runs.setdefault(t["method"], []).append(t)
        cells = [
            " / ".join(f"{t['add_mean_mm']:.2f} [{t['diverged_frames']}]" for t in runs[m]) if m in runs else "-"
            for m in methods
        ]
        first_track = next(t for t in tracks if t["trajectory"] == name)
        ratio = first_track.get("open_loop_force_ratio")
        drift = (
            f"{first_track['open_loop_mean_mm']:.1f} / {first_track['open_loop_max_mm']:.1f}"
            + (f" x{ratio:.2f}" if ratio is not None else "")
            if "open_loop_mean_mm" in first_track
            else "-"
        )
        lines.append(f"| {name} | {drift} | " + " | ".join(cells) + " |")
        series = {m: np.asarray(runs[m][0]["add_mm"]) for m in methods if m in runs}  # the first run's
        line_chart(out / f"add_{name}.png", f"{name} {noise}", series, x_step=1 / 30,
                   note=_what_ran(results, "ADD of each method's estimate per frame, the first run"))  # fmt: skip
    first = " (the first run)" if results.get("repeats", 1) > 1 else ""
    return [*lines, "", f"ADD over time per trajectory{first}:", ""] + [f"![{n}](add_{n}.png)" for n in names]


def _table(summary: dict, methods: list[str], noises: list[str]) -> list[str]:
    """A Fig. 2 table: one row per method, one column per noise level."""
    lines = [
        "| method | "
        + " | ".join(f"{n} ({NOISE_LEVELS[n][0] * 1e3:g} mm, {NOISE_LEVELS[n][1]:g} rad)" for n in noises)
        + " |",
        "|---|" + "---|" * len(noises),
    ]
    for m in methods:
        cells = [_cell(s) if (s := summary[m].get(n)) else "-" for n in noises]
        lines.append(f"| {m} | " + " | ".join(cells) + " |")
    return lines


def _runs(s: dict) -> str:
    """A mean ADD [mm], with each run's mean when the suite was repeated."""
    runs = s.get("run_means_mm")
    return f"{s['mean_mm']:.2f}" + (f" [{' / '.join(f'{r:.2f}' for r in runs)}]" if runs else "")


def _cell(s: dict) -> str:
    return f"{_runs(s)} ± {s['std_mm']:.2f} (max {s['max_mm']:.1f})"
