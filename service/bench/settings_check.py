"""Which tracker settings a robot should run, from its own recordings with truth (motion capture):
the population with the robot's settings and with each candidate table, against one open-loop world
from the same noisy starts, and the overlay of its config that carries the table to run.

Whether a robot's sensing ranks its worlds' object poses, or only their physics and noise, cannot
be told from the sensing alone: the worlds' costs separate them in both cases. The truth of a few
grasps tells it: where the population is worse than one open-loop world, the robot needs settings
that fall back to dead reckoning while its costs do not tell the poses apart."""

from __future__ import annotations

import datetime
import json
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from inhand_tracker.protocol import Trajectory
from inhand_tracker.service.tracker.settings import robot_defaults, tracker_config
from inhand_tracker.sim_backend import RobotSpec

from .accuracy import files_suite
from .progress import progress_bar
from .run import AccuracyRun
from .tracks import plan_tracks, run_tracks

__all__ = ["CANDIDATES", "OWN_SETTINGS", "SettingsCheck", "check_settings", "settings_report", "write_settings"]

CANDIDATES: dict[str, dict[str, bool | int | float | str]] = {
    "palm": {"optimizer.open_loop_ratio": 1.5, "optimizer.min_pose_evidence": 10.0},
    "until felt": {"optimizer.until_felt": True},
    "from the first window": {"optimizer.until_felt": False},
}
"""Tables tried beside the robot's own settings (one that leaves them as they are is not run twice).
``palm``: report the open-loop world while it explains the robot as well as the population's best,
and resample the object poses only where they explain the costs beyond the physics (an object lying
on a palm, felt through its weight or through fingertips that rarely touch it). ``until felt``: hold
the worlds and report the open-loop world until the robot first feels the object; ``from the first
window``: update from the start (the defaults, where a palm-carrying robot's config has no table)."""

OWN_SETTINGS = "robot's settings"
"""The name of the robot's own settings (its config's ``[tracker]`` table, or what a config without
one runs: :func:`..tracker.settings.robot_defaults`)."""

_Z95 = 1.645
"""The standard normal's one-sided 95 % quantile."""


def _paired(d: np.ndarray) -> tuple[float, float]:
    """The mean of paired differences ``d`` (N,) and its standard error (0 for one pair)."""
    return float(d.mean()), float(d.std(ddof=1) / np.sqrt(d.size)) if d.size > 1 else 0.0


@dataclass
class SettingsCheck:
    """Mean ADD of each setting on every (recording, start) pair, [m], paired with one open-loop
    world from the same start."""

    robot: str
    method: str
    worlds: int
    device: str
    tracks: list[str]
    """The recording of each pair, (N,)."""
    one_world: np.ndarray
    """One open-loop world's mean ADD per pair, (N,) [m]."""
    runs: dict[str, np.ndarray] = field(default_factory=dict)
    """Each setting's mean ADD per pair, (N,) [m]: :data:`OWN_SETTINGS` first, then the candidates."""
    tables: dict[str, dict[str, bool | int | float | str]] = field(default_factory=dict)
    """Each setting's whole ``[tracker]`` table by dotted name: the robot's with the candidate's."""

    def allowance(self) -> float:
        """How much worse than one world a setting may be: max(0.2 mm, 5 % of its mean ADD) [m]."""
        return max(0.2e-3, 0.05 * float(self.one_world.mean()))

    def paired(self, name: str) -> tuple[float, float]:
        """The mean difference of setting ``name`` from one world over the pairs and its standard
        error [m] (0 from a single pair, which has no spread to tell)."""
        return _paired(self.runs[name] - self.one_world)

    def upper(self, name: str) -> float:
        """The one-sided 95 % bound of :meth:`paired`'s difference, mean + 1.645 standard errors [m]."""
        mean, se = self.paired(name)
        return mean + _Z95 * se

    def within(self, name: str) -> bool:
        """Whether setting ``name`` is surely no worse than one world by more than :meth:`allowance`:
        its :meth:`upper` bound within it, not its mean alone, which a few lucky starts can bring under."""
        return self.upper(name) <= self.allowance()

    def chosen(self) -> str:
        """The setting to run: the lowest mean ADD among those :meth:`within`, but the robot's own
        where it is within and that one is not surely better (its paired gain over one standard error);
        where none is, the one with the lowest :meth:`upper` bound."""
        within = [n for n in self.runs if self.within(n)]
        if not within:
            return min(self.runs, key=self.upper)
        best = min(within, key=lambda n: self.runs[n].mean())
        if OWN_SETTINGS in within and best != OWN_SETTINGS:
            gain, se = _paired(self.runs[OWN_SETTINGS] - self.runs[best])
            if gain <= se:
                return OWN_SETTINGS
        return best

    def _setting(self, name: str) -> dict:
        """One setting's line of :meth:`summary`."""
        mean, se = self.paired(name)
        return {
            "mean_mm": 1e3 * float(self.runs[name].mean()),
            "vs_one_world_mm": 1e3 * mean,
            "standard_error_mm": 1e3 * se,
            "upper_mm": 1e3 * self.upper(name),
            "within_limit": self.within(name),
            "table": self.tables[name],
        }

    def summary(self) -> dict:
        """Everything the report says, JSON-ready, in mm: per setting its mean, its paired difference
        from one world, the difference's standard error and bound, whether it is within, its table."""
        return {
            "robot": self.robot,
            "method": self.method,
            "worlds": self.worlds,
            "device": self.device,
            "pairs": len(self.tracks),
            "one_world_mm": 1e3 * float(self.one_world.mean()),
            "allowance_mm": 1e3 * self.allowance(),
            "settings": {name: self._setting(name) for name in self.runs},
            "chosen": self.chosen(),
        }


def check_settings(
    spec: RobotSpec,
    trajectories: Sequence[Trajectory],
    worlds: int = 40,
    starts: int = 3,
    noise: str = "med",
    device: str = "auto",
    candidates: Mapping[str, Mapping[str, bool | int | float | str]] = CANDIDATES,
    quiet: bool = False,
) -> SettingsCheck:
    """Track ``trajectories`` (each with its truth, as :func:`.accuracy.load_files` reads them) with
    ``spec``'s settings and with each of ``candidates`` over them, ``starts`` noisy starts per
    recording (``noise``, a bench level), and with one open-loop world from the same starts. The
    population runs the method its settings name. A ValueError names a recording of another robot."""
    for t in trajectories:
        if t.robot != spec.name:
            raise ValueError(f"recording '{t.name}' is of robot '{t.robot}', the config's is '{spec.name}'")
    own = robot_defaults(spec)
    base = tracker_config(own)
    tables = {OWN_SETTINGS: own} | {name: own | dict(table) for name, table in candidates.items()}
    tables = {n: t for n, t in tables.items() if n == OWN_SETTINGS or tracker_config(t) != base}
    method = base.optimizer.method
    by_object: dict[str, list[Trajectory]] = {}
    for t in trajectories:
        by_object.setdefault(t.object, []).append(t)
    adds: dict[str, list[float]] = {}
    names: list[str] = []
    frames = max(t.frames for t in trajectories)
    per_start = len(trajectories) * (1 + worlds * len(tables))  # OLP's one world, then each setting's
    bar = progress_bar(frames * per_start * starts, "tracking", unit="world-frames", disable=quiet)
    for i, (name, table) in enumerate(tables.items()):
        methods = ("OLP", method) if i == 0 else (method,)
        run = AccuracyRun(
            files_suite(trajectories), methods, (noise,), worlds, repeats=starts, config=tracker_config(table),
            device=device, cache=None, quiet=quiet, files=tuple(trajectories), robot=spec,
        )  # fmt: skip
        for ts in by_object.values():
            plan = plan_tracks(len(ts), methods, (noise,), (), worlds, repeats=starts)
            results = run_tracks(ts, plan, run, bar.update)
            # Sorted by (recording, start), so that every setting's pairs line up with one world's.
            results.sort(key=lambda r: (r.trajectory, r.setting.repeat))
            for r in results:
                key = "one world" if r.setting.method == "OLP" else name
                adds.setdefault(key, []).append(float(r.add.mean()))
                if i == 0 and r.setting.method == "OLP":
                    names.append(r.trajectory)
    bar.close()
    return SettingsCheck(
        spec.name, method, worlds, device, names, np.array(adds.pop("one world")),
        {n: np.array(adds[n]) for n in tables}, tables,
    )  # fmt: skip


def settings_report(check: SettingsCheck) -> str:
    """A markdown table: each setting's mean ADD, its paired difference from one open-loop world
    with the difference's standard error and 95 % bound, whether it is surely within the allowance,
    and the setting chosen."""
    s = check.summary()
    lines = [
        f"Robot '{check.robot}', {check.method} with {check.worlds} worlds, {s['pairs']} (recording, start) pairs"
        f" ({check.device}): one open-loop world {s['one_world_mm']:.2f} mm; a setting may be worse by"
        f" {s['allowance_mm']:.2f} mm at its 95 % bound.",
        "",
        "| settings | mean ADD mm | vs one world mm | 95 % bound mm | within | table |",
        "|---|---|---|---|---|---|",
    ]
    for name, r in s["settings"].items():
        table = ", ".join(f"{k}={v}" for k, v in r["table"].items()) or "defaults"
        lines.append(
            f"| {name} | {r['mean_mm']:.2f} | {r['vs_one_world_mm']:+.2f} ± {r['standard_error_mm']:.2f} |"
            f" {r['upper_mm']:+.2f} | {'yes' if r['within_limit'] else 'no'} | {table} |"
        )
    lines += ["", f"Chosen: {s['chosen']}."]
    return "\n".join(lines)


def write_settings(check: SettingsCheck, config: Path, out: Path, command: str = "") -> Path | None:
    """Write the overlay of ``config`` with the chosen setting's ``[tracker]`` table to ``out``, and
    the report beside it as ``.md`` and ``.json``; returns the overlay's path, or None where the
    robot's own settings are chosen (its config stays as it is, and ``out`` is not written)."""
    chosen = check.chosen()
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".md").write_text(settings_report(check) + "\n")
    out.with_suffix(".json").write_text(json.dumps(check.summary(), indent=2))
    if chosen == OWN_SETTINGS:
        return None
    mean, se = (1e3 * x for x in check.paired(chosen))
    lines = [
        f"# Robot '{check.robot}' with the tracker settings chosen on its own recordings"
        + (f" by `{command}`" if command else "")
        + f" on {datetime.date.today().isoformat()} ({check.device}):",
        f"# {check.method} with {check.worlds} worlds, {mean:+.2f} ± {se:.2f} mm against one open-loop world"
        f" ({1e3 * check.one_world.mean():.2f} mm) over {len(check.tracks)} (recording, start) pairs.",
        "# Name this file in the service's `robots` setting in place of the config.",
        f'extends = "{Path(os.path.relpath(config.resolve(), out.resolve().parent)).as_posix()}"',
        "",
        "[tracker]",
        # A dotted key under [tracker] is the nested table the config reads; a JSON scalar
        # (number, true/false, quoted string) is a TOML one.
        *(f"{k} = {json.dumps(v)}" for k, v in check.tables[chosen].items()),
        "",
    ]
    out.write_text("\n".join(lines))
    return out
