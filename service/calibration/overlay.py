"""What a calibration leaves beside the robot's config: an overlay that the service loads in its
place (the config with the fitted servos), and a report of what was fitted and how well."""

from __future__ import annotations

import datetime
import json
import os
from pathlib import Path

import numpy as np

from .servos import STAYS_OFF, ServoFit

__all__ = ["calibration_report", "write_overlay"]


def _numbers(values: np.ndarray) -> str:
    return "[" + ", ".join(f"{v:.6g}" for v in values) + "]"


def write_overlay(fit: ServoFit, config: Path, out: Path | None = None, command: str = "") -> Path:
    """Write the overlay of ``config`` with ``fit``'s servos (default ``NAME.calibrated.toml``
    beside it), and its report beside it as ``.md`` (:func:`calibration_report`) and ``.json``
    (:meth:`ServoFit.summary`); returns the overlay's path."""
    out = out or config.with_name(f"{config.stem}.calibrated.toml")
    before, after = (float(np.sqrt(np.mean(r**2))) * 1e3 for r in (fit.rms_before, fit.rms_after))
    lines = [
        f"# Robot '{fit.robot}' with its servos fitted to its own recordings"
        + (f" by `{command}`" if command else "")
        + f" on {datetime.date.today().isoformat()} ({fit.device}):",
        f"# joint RMS error {before:.2f} -> {after:.2f} mrad (mm for slides) over {fit.frames} frames;",
        f"# {int(fit.identified.sum())} of {fit.identified.size} joints take their fitted servos, the others keep the"
        f" config's (the fit did not lower their error, or left them more than {STAYS_OFF * 1e3:.0f} mrad off).",
        "# Name this file in the service's `robots` setting in place of the config.",
        f'extends = "{Path(os.path.relpath(config.resolve(), out.resolve().parent)).as_posix()}"',
        "",
        "[servos]  # one value per joint, in the config's joint order",
        *(f"{s} = {_numbers(fit.fitted[s])}" for s in fit.settings),
        "",
    ]
    out.write_text("\n".join(lines))
    out.with_suffix(".md").write_text(calibration_report(fit))
    out.with_suffix(".json").write_text(json.dumps(fit.summary(), indent=2))
    return out


def calibration_report(fit: ServoFit) -> str:
    """A markdown table per joint: RMS joint error before and after, each setting's fitted value
    against the config's with its spread, and whether the data excited the joint."""
    noisy = fit.joint_noise > 0
    net = " | RMS after, net of noise" if noisy else ""
    head = f"| joint | RMS before | RMS after{net} | " + " | ".join(fit.settings) + " |"
    rows = [head, "|" + "---|" * (3 + noisy + len(fit.settings))]
    after_net = fit.net(fit.rms_after)
    for j, name in enumerate(fit.joints):
        cells = []
        for s in fit.settings:
            nominal, fitted, spread = fit.nominal[s][j], fit.fitted[s][j], fit.spread[s][j]
            cells.append(
                f"{fitted:.4g} (config {nominal:.4g}, ±{spread * 100:.0f} %)"
                if fit.identified[j]
                else f"{nominal:.4g} kept (±{spread * 100:.0f} %)"
            )
        note = "" if fit.excited[j] else " (not excited)"
        errors = f"{fit.rms_before[j] * 1e3:.2f} | {fit.rms_after[j] * 1e3:.2f}"
        errors += f" | {after_net[j] * 1e3:.2f}" if noisy else ""
        rows.append(f"| {name}{note} | {errors} | " + " | ".join(cells) + " |")
    quiet = [n for n, e in zip(fit.joints, fit.excited, strict=True) if not e]
    named = zip(fit.joints, fit.net(fit.rms_fit), fit.excited, strict=True)
    off = [f"{n} {e * 1e3:.0f}" for n, e, excited in named if excited and e > STAYS_OFF]
    return "\n".join(
        [
            f"# Servo calibration of `{fit.robot}`",
            "",
            f"{fit.worlds} candidates a generation, {fit.generations} generations, {fit.frames} frames,"
            f" {fit.seconds:.0f} s. RMS joint error in mrad (mm for slides); a joint keeps its fitted servo where"
            f" that lowers its own error by 5 % or more and leaves it within {STAYS_OFF * 1e3:.0f} mrad net of the"
            " noise; a setting's spread is how far the best quarter of the"
            " last generation disagrees."
            + (
                f" The measured joints carry {fit.joint_noise * 1e3:.2g} mrad (mm) of noise, which no model follows:"
                " net of it, the error is the square root of the difference of the squares."
                if noisy
                else ""
            ),
            "",
            *rows,
            "",
            f"Joints the recording did not excite (moved less than a tenth of their range): {', '.join(quiet)}"
            if quiet
            else "Every joint was excited.",
            "",
            *(
                [
                    f"Joints the fit leaves more than {STAYS_OFF * 1e3:.0f} mrad (mm) off, net of the noise, keep"
                    f" the config's servos: {', '.join(off)}. Their model differs in more than its servos (a"
                    " coupling, a contact, a mass): a fitted servo there would stand in for what is missing and"
                    " press harder than the robot.",
                    "",
                ]
                if off
                else []
            ),
        ]
    )
