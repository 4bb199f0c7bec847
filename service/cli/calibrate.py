"""The robot's model against its own data: `check-model` says how far one world of its config
follows a recording and what to change; `calibrate` fits its servos and writes them as an overlay."""

from __future__ import annotations

import contextlib
import json
import sys
from pathlib import Path
from typing import Annotated

import typer

from .common import Device, ExitCode, Json, app, check_device, command_line, fail, gpu_stack, names


def _files_exist(command: str, robot: Path, recordings: list[Path], device: str) -> None:
    """Refuse a missing config or recording before the GPU stack loads (seconds), naming it."""
    check_device(device, command)
    if not robot.is_file():
        raise fail(f"{command} --robot: no such file '{robot}'", ExitCode.FILES)
    if missing := [str(r) for r in recordings if not r.exists()]:
        raise fail(f"{command}: no such recording {missing[0]}", ExitCode.FILES)
    gpu_stack()


@app.command()
def calibrate(
    ctx: typer.Context,
    recordings: Annotated[list[Path], typer.Argument(help="recordings: .traj, or the service's (folder or .mcap)")],
    robot: Annotated[Path, typer.Option(help="the robot's config (TOML) the recordings were made with")],
    settings: Annotated[
        str, typer.Option(help="what to fit, comma-separated: ke, kd, effort, damping, armature, friction")
    ] = "ke,kd",
    worlds: Annotated[int, typer.Option(help="candidates per generation (worlds of the population)")] = 64,
    generations: Annotated[int, typer.Option(help="CMA-ES generations, each a replay of the recordings")] = 25,
    object_: Annotated[
        str | None, typer.Option("--object", help="what the worlds simulate beside the hand (default: the recordings')")
    ] = None,
    out: Annotated[Path | None, typer.Option(help="the overlay (default: NAME.calibrated.toml beside it)")] = None,
    joint_noise: Annotated[
        float, typer.Option(help="the measured joints' noise, a standard deviation [rad or m]: the report takes it out")
    ] = 0.0,
    device: Device = "auto",
    json_: Json = False,
) -> None:
    """Fit the robot's position servos to its recordings (commands and measured joints) and write
    an overlay of its config with them, and a report: joint error before and after, the fitted
    values with their spread, and the joints the recordings did not excite."""
    _files_exist("calibrate", robot, recordings, device)
    from inhand_tracker.protocol.recording import load_trajectory
    from inhand_tracker.service.calibration import calibration_report, fit_servos, write_overlay
    from inhand_tracker.sim_backend import catalog_object, load_robot

    try:
        spec = load_robot(robot)
        trajs = [load_trajectory(r) for r in recordings]
        obj = catalog_object(object_ or trajs[0].object)
        with contextlib.redirect_stdout(sys.stderr):
            fit = fit_servos(
                spec, obj, trajs, settings=tuple(names(settings) or ()), worlds=worlds, generations=generations,
                device=device, joint_noise=joint_noise,
            )  # fmt: skip
    except ValueError as exc:
        raise fail(f"calibrate: {exc}") from None
    overlay = write_overlay(fit, robot, out, command_line(ctx))
    typer.echo(json.dumps(fit.summary(), indent=2) if json_ else calibration_report(fit))
    typer.echo(f"overlay: {overlay}\nreport: {overlay.with_suffix('.md')}", err=json_)


@app.command("check-model")
def check_model(
    recordings: Annotated[list[Path], typer.Argument(help="recordings with truth: .traj (or the service's)")],
    robot: Annotated[Path, typer.Option(help="the robot's config (TOML)")],
    joint_noise: Annotated[
        float, typer.Option(help="the measured joints' noise, a standard deviation [rad or m]: taken out of the RMS")
    ] = 0.0,
    variants: Annotated[bool, typer.Option(help="also try changes of the model and say which help")] = True,
    set_: Annotated[
        list[str] | None,
        typer.Option(
            "--set", metavar="NAME=VALUE", help="the physics the service runs, e.g. population.integrator=euler"
        ),
    ] = None,
    device: Device = "auto",
    json_: Json = False,
) -> None:
    """Replay each recording open loop in one world of the robot's config from its true start, and
    report per joint the RMS error net of noise, how hard the worlds press against what the robot
    felt, the object's drift, the largest mismatches, and which change of the model brings the
    worlds closest (impratio, the friction cone, a joint's servo). Run it before tracking."""
    _files_exist("check-model", robot, recordings, device)
    from inhand_tracker.protocol.recording import load_trajectory
    from inhand_tracker.service.calibration.model_check import check_model as check
    from inhand_tracker.service.calibration.model_check import model_check_report
    from inhand_tracker.service.tracker import settings
    from inhand_tracker.sim_backend import load_robot

    try:
        physics = settings.split(
            settings.parse(set_ or [], [n for n in settings.registry() if n.startswith("population.")])
        )[1]
        spec = load_robot(robot)
        trajs = [load_trajectory(r) for r in recordings]
        with contextlib.redirect_stdout(sys.stderr):
            result = check(spec, trajs, device=device, joint_noise=joint_noise, variants=variants, physics=physics)
    except ValueError as exc:
        raise fail(f"check-model: {exc}") from None
    typer.echo(json.dumps(result.summary(), indent=2) if json_ else model_check_report(result))


@app.command("check-settings")
def check_settings(
    ctx: typer.Context,
    recordings: Annotated[list[Path], typer.Argument(help="recordings with truth (motion capture): .traj")],
    robot: Annotated[Path, typer.Option(help="the robot's config (TOML)")],
    worlds: Annotated[int, typer.Option(help="K, worlds per recording, as the service will run it")] = 40,
    starts: Annotated[int, typer.Option(help="noisy starts per recording, each paired with one world's")] = 3,
    noise: Annotated[str, typer.Option(help="the start's error: low, med or high (the benchmarks' levels)")] = "med",
    set_: Annotated[
        list[str] | None,
        typer.Option(
            "--set", metavar="NAME=VALUE", help="a table of your own to try as well, e.g. optimizer.by_evidence=true"
        ),
    ] = None,
    out: Annotated[Path | None, typer.Option(help="the overlay (default: NAME.tracker.toml beside it)")] = None,
    device: Device = "auto",
    json_: Json = False,
) -> None:
    """Track the recordings with the robot's tracker settings and with the candidate tables (the palm
    settings, holding the worlds until the robot feels the object or updating from the first window,
    and the one ``--set`` gives), each paired with one open-loop world from the same
    starts, and write an overlay of the config with the table that tracks best of those surely no
    worse than that world, and a report."""
    _files_exist("check-settings", robot, recordings, device)
    from inhand_tracker.service.bench import CANDIDATES, OWN_SETTINGS, settings_report, write_settings
    from inhand_tracker.service.bench import check_settings as check
    from inhand_tracker.service.bench.accuracy import load_files
    from inhand_tracker.service.bench.suites import NOISE_LEVELS
    from inhand_tracker.service.tracker import settings
    from inhand_tracker.sim_backend import load_robot

    if noise not in NOISE_LEVELS:
        raise fail(f"check-settings --noise: expected one of {sorted(NOISE_LEVELS)}, got '{noise}'")
    if worlds < 2 or starts < 1:
        raise fail(f"check-settings: expected --worlds >= 2 and --starts >= 1, got {worlds} and {starts}")
    try:
        given = settings.parse(set_ or [], [n for n in settings.registry() if not n.startswith("population.")])
    except ValueError as exc:
        raise fail(f"check-settings --set: {exc}") from None
    candidates = CANDIDATES | ({"given": given} if given else {})
    try:
        spec = load_robot(robot)
        trajs = load_files(recordings)
        with contextlib.redirect_stdout(sys.stderr):
            result = check(spec, trajs, worlds, starts, noise, device, candidates)
    except ValueError as exc:
        raise fail(f"check-settings: {exc}") from None
    target = out or robot.with_name(f"{robot.stem}.tracker.toml")
    overlay = write_settings(result, robot, target, command_line(ctx))
    typer.echo(json.dumps(result.summary(), indent=2) if json_ else settings_report(result))
    said = f"overlay: {overlay}" if overlay else "the robot's settings are chosen: its config stays as it is"
    if overlay is None and spec.tracker is None:
        table = ", ".join(f"{k} = {json.dumps(v)}" for k, v in result.tables[OWN_SETTINGS].items())
        said += f" (add `tracker = {{{f' {table} ' if table else ''}}}` to it to record these settings as chosen)"
    typer.echo(f"{said}\nreport: {target.with_suffix('.md')}", err=json_)
