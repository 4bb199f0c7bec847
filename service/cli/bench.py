"""`inhand-tracker bench ...`: accuracy, speed, load, the physics alone, cost ranking, the docs page."""

from __future__ import annotations

import contextlib
import json
import logging
import sys
import time
from pathlib import Path
from typing import Annotated

import typer

from .common import Device, IntList, Json, bench, command_line, fail, gpu_stack, names, suite_named

log = logging.getLogger("inhand_tracker")


@contextlib.contextmanager
def _running(name: str):
    """A benchmark's run: what a library prints goes to stderr (stdout is for the table or the
    JSON), and a ValueError is the command's one-line refusal."""
    try:
        with contextlib.redirect_stdout(sys.stderr):
            yield
    except ValueError as exc:
        raise fail(f"bench {name}: {exc}") from None


@bench.command("sim")
def bench_sim(
    worlds: IntList = "40,256,1024,4096",
    substeps: IntList = None,
    solver: Annotated[str, typer.Option(help="MuJoCo solvers: auto (newton), cg, newton")] = "auto",
    frames: Annotated[int, typer.Option(help="timed frames per K")] = 60,
    object: Annotated[str, typer.Option(help="catalog object held in the grasp")] = "foam_brick",
    device: Device = "auto",
    json_: Json = False,
) -> None:
    """The physics population alone: ms per 30 Hz frame and memory per world."""
    gpu_stack()
    from inhand_tracker.service.bench.sim import as_dicts, bench_sim
    from inhand_tracker.service.bench.sim import format_table as table
    from inhand_tracker.sim_backend import PopulationConfig

    results = []
    for name in solver.split(","):
        for n in substeps or [PopulationConfig.substeps]:
            results += bench_sim(worlds, substeps=n, frames=frames, obj=object, device=device, solver=name)
    typer.echo(json.dumps(as_dicts(results), indent=2) if json_ else table(results))


@bench.command("speed")
def bench_speed(
    ctx: typer.Context,
    worlds: IntList = "40,256,1024,4096,8192",
    groups: IntList = "1",
    substeps: IntList = None,
    jacobian: Annotated[str | None, typer.Option(help="constraint Jacobians, e.g. dense,sparse")] = None,
    caps: Annotated[
        str, typer.Option(help="solver caps ITERATIONSxLINE_SEARCH, comma-separated; default: the solver's own")
    ] = "default",
    frames: Annotated[int, typer.Option(help="timed frames per size (after 30 warm-up frames)")] = 200,
    set_: Annotated[
        list[str] | None,
        typer.Option("--set", metavar="population.NAME=VALUE", help="a physics setting: population.tolerance=1e-4"),
    ] = None,
    device: Device = "auto",
    json_: Annotated[bool, typer.Option("--json", help="print JSON (device, date, command, results)")] = False,
) -> None:
    """The whole tracker frame (frame in, estimate out) against the physics alone."""
    gpu_stack()
    from inhand_tracker.service.bench import parse_settings
    from inhand_tracker.service.bench.speed import as_dicts, bench_speed, format_table
    from inhand_tracker.service.server.budget import device_name
    from inhand_tracker.service.tracker import TrackerConfig
    from inhand_tracker.sim_backend import PopulationConfig, resolve_device

    try:
        solver_caps = [(None, None) if c == "default" else tuple(int(v) for v in c.split("x")) for c in names(caps)]
        if any(len(c) != 2 for c in solver_caps):
            raise ValueError
    except ValueError:
        text = f"bench speed: caps: expected ITERATIONSxLINE_SEARCH or default, comma-separated, got {caps!r}"
        raise fail(text) from None
    try:
        config, physics = parse_settings(set_ or [])
        if config != TrackerConfig():
            raise ValueError(f"expected population.NAME=VALUE (the physics), got {set_}")
    except ValueError as exc:
        raise fail(f"bench speed: --set: {exc}") from None

    def show(r) -> None:
        log.info(
            "W=%d G=%d substeps=%d %s: tracker %.2f ms (p99 %.2f), physics %.2f ms, ratio %.2f",
            r.worlds, r.groups, r.substeps, r.solver, r.tracker_median_ms, r.tracker_p99_ms,
            r.physics_median_ms, r.ratio,
        )  # fmt: skip

    with _running("speed"):
        results = bench_speed(
            worlds,
            groups,
            substeps or [PopulationConfig.substeps],
            frames=frames,
            device=device,
            caps=solver_caps,
            physics=physics,
            progress=show,
            **({"jacobians": jacobian.split(",")} if jacobian else {}),
        )
    if json_:
        head = {"device": device_name(resolve_device(device)), "date": time.strftime("%Y-%m-%d")}
        head["command"] = command_line(ctx)
        typer.echo(json.dumps({**head, "results": as_dicts(results)}, indent=1))
    else:
        typer.echo(format_table(results))


@bench.command("load")
def bench_load(
    sessions: Annotated[int, typer.Option(help="robots streaming at once, one session each")] = 4,
    worlds: Annotated[int, typer.Option(help="K per session")] = 40,
    rate: Annotated[float, typer.Option(help="each robot's frames per second")] = 30.0,
    seconds: Annotated[float, typer.Option(help="how long the robots stream")] = 10.0,
    connect: Annotated[
        str, typer.Option(help="a running service's endpoints, comma-separated (default: embed one)")
    ] = "",
    churn: Annotated[bool, typer.Option(help="another peer opens with new settings all the while (builds)")] = False,
    device: Device = "auto",
    json_: Json = False,
) -> None:
    """The service under load: N robots at a fixed rate; estimates per second, latency, late frames."""
    gpu_stack()
    from inhand_tracker.service.bench.load import as_dicts, bench_load, format_table

    with _running("load"):
        results = bench_load(sessions, worlds, rate, seconds, device, connect=tuple(names(connect)), churn=churn)
    typer.echo(json.dumps(as_dicts(results), indent=2) if json_ else format_table(results))


SUITE_HELP = (
    "smoke, paper, reality-gap, cross-engine (+ -shadow), manipulate (+ -fingertips), manipulate-egg and"
    " manipulate-pen (+ -fingertips), allegro-palm (+ -grid, -weak, -fingertips) or loss"
)


@bench.command("accuracy")
def bench_accuracy(
    ctx: typer.Context,
    suite: Annotated[str, typer.Option(help=SUITE_HELP)] = "smoke",
    short: Annotated[bool, typer.Option(help="the suite in short form: one object, two kinds, 10 s tracks")] = False,
    methods: Annotated[str, typer.Option(help="comma-separated: OLP, EYE, WRS, REPS, PBO")] = "OLP,EYE,WRS,REPS,PBO",
    noise: Annotated[str, typer.Option(help="initial pose noise levels: low, med, high")] = "low,med,high",
    worlds: Annotated[int | None, typer.Option(help="K, worlds per track (default: the protocol's)")] = None,
    ablations: Annotated[str, typer.Option(help="comma-separated: exploration, worlds, contact, slip, or all")] = "",
    ablation_worlds: IntList = None,
    substeps: Annotated[int | None, typer.Option(help="the tracker's physics substeps per frame")] = None,
    repeats: Annotated[int, typer.Option(help="independent runs of every track, batched; each run's mean")] = 1,
    set_: Annotated[
        list[str] | None,
        typer.Option("--set", metavar="NAME=VALUE", help="a tracker or physics setting, e.g. population.impratio=30"),
    ] = None,
    observations: Annotated[
        str, typer.Option(help="a camera's pose estimates: none, ends (first and last frame), 1hz, visible")
    ] = "none",
    vision_sigma: Annotated[
        str, typer.Option(help="their noise, position [m] and rotation [rad], comma-separated")
    ] = "0.005,0.05",
    files: Annotated[
        str | None,
        typer.Option(help="score your own .traj files (with ground truth) instead of a suite, comma-separated"),
    ] = None,
    robot_overlay: Annotated[
        Path | None,
        typer.Option(help="the tracker's servos from this calibration overlay (`calibrate`); the truth keeps its own"),
    ] = None,
    device: Device = "auto",
    out: Annotated[Path | None, typer.Option(help="output folder (default bench-results/accuracy-SUITE)")] = None,
    cache: Annotated[Path | None, typer.Option(help="where generated trajectories are kept")] = None,
    save_frames: Annotated[
        bool, typer.Option(help="also write frames.npz: each frame's error, reported covariance and cost")
    ] = False,
    json_: Json = False,
) -> None:
    """Tracking accuracy (ADD) on synthetic ground truth, as the paper's IV-A."""
    gpu_stack()
    from inhand_tracker.service.bench import K_ABLATION, AccuracyRun, run_suite, write_report
    from inhand_tracker.service.bench.run import ABLATIONS
    from inhand_tracker.service.paths import CACHE_DIR

    chosen_suite, mine, servos = _what_to_track(suite, short, files, robot_overlay)
    config, population = _settings(set_ or [], chosen_suite.robot)
    out = out or Path(f"bench-results/accuracy-{chosen_suite.name}")
    command = command_line(ctx)
    chosen = {k: v for k, v in {"worlds": worlds, "substeps": substeps}.items() if v}
    try:
        run = AccuracyRun(
            chosen_suite,
            files=mine,
            methods=tuple(names(methods)),
            noises=tuple(names(noise)),
            ablations=tuple(ABLATIONS if ablations == "all" else names(ablations)),
            k_ablation=tuple(ablation_worlds or K_ABLATION),
            repeats=repeats,
            config=config,
            population=population,
            observations=observations,
            vision_sigma=_vision_sigma(vision_sigma),
            device=device,
            cache=cache or CACHE_DIR,
            frames_to=out / "frames.npz" if save_frames else None,
            servos=servos,
            **chosen,
        )
        with contextlib.redirect_stdout(sys.stderr):  # anything a library prints; stdout is for the report or JSON
            results = run_suite(run, checkpoint=lambda part: write_report(part, out, command=command + "  (partial)"))
    except ValueError as exc:
        raise fail(f"bench accuracy: {exc}") from None
    report = write_report(results, out, command=command)
    summary = {"summary": results["summary"], "ablations": results["ablations"]}
    text = report.read_text().split("\n## Ablation")[0].split("\n## Per trajectory")[0] + f"\nreport: {report}"
    typer.echo(json.dumps(summary, indent=2) if json_ else text)


@bench.command("calibration")
def bench_calibration(
    ctx: typer.Context,
    suite: Annotated[str, typer.Option(help=SUITE_HELP)] = "manipulate",
    seconds: Annotated[float, typer.Option(help="length of the excitation recording [s]")] = 20.0,
    settings: Annotated[
        str, typer.Option(help="what to fit, comma-separated: ke, kd, effort, damping, armature, friction")
    ] = "ke,kd",
    worlds: Annotated[int, typer.Option(help="candidates per generation")] = 128,
    generations: Annotated[int, typer.Option(help="CMA-ES generations")] = 30,
    device: Device = "auto",
    out: Annotated[Path | None, typer.Option(help="output folder (default bench-results/calibration-SUITE)")] = None,
) -> None:
    """The suite's excitation recording (its robot moving every joint, the object out of reach,
    recorded by the suite's truth), and the tracker's servos fitted to it: an overlay of the robot's
    config for `bench accuracy --robot-overlay`, and a report."""
    gpu_stack()
    from inhand_tracker.service.bench.excitation import excitation_recording
    from inhand_tracker.service.bench.suites import robot_spec
    from inhand_tracker.service.calibration import calibration_report, fit_servos, write_overlay
    from inhand_tracker.service.paths import CONFIG_DIR
    from inhand_tracker.sim_backend import catalog_object

    chosen = suite_named(suite, False)
    out = out or Path(f"bench-results/calibration-{suite}")
    out.mkdir(parents=True, exist_ok=True)
    with _running("calibration"):
        traj = excitation_recording(chosen, device, seconds)
        traj.save(out / f"{suite}-calibration.traj")
        spec, obj = robot_spec(chosen.robot), catalog_object(traj.object)
        fit = fit_servos(
            spec, obj, [traj], tuple(names(settings) or ()), worlds, generations, device,
            joint_noise=chosen.sensors.joint_sigma,
        )  # fmt: skip
    config = CONFIG_DIR / "robots" / f"{chosen.robot}.toml"
    overlay = write_overlay(fit, config, out / f"{chosen.robot}.calibrated.toml", command_line(ctx))
    typer.echo(calibration_report(fit) + f"\noverlay: {overlay}")


def _vision_sigma(text: str) -> tuple[float, float]:
    """``--vision-sigma`` as (position [m], rotation [rad]), or exit 2 naming it."""
    try:
        sigma_t, sigma_r = (float(v) for v in text.split(","))
    except ValueError:
        raise fail(f"bench accuracy: vision-sigma: expected POSITION,ROTATION, got {text!r}") from None
    return sigma_t, sigma_r


def _settings(items: list[str], robot: str) -> tuple:
    """The tracker's settings and physics: ``robot``'s own changed by ``--set``, or exit 2 naming what is wrong."""
    from inhand_tracker.service.bench import parse_settings
    from inhand_tracker.service.bench.suites import robot_spec
    from inhand_tracker.service.tracker.settings import robot_defaults

    try:
        defaults = robot_defaults(robot_spec(robot))
    except ValueError as exc:
        raise fail(f"bench accuracy: {exc}") from None
    try:
        return parse_settings(items, defaults)
    except ValueError as exc:
        raise fail(f"--set: {exc}") from None


def _what_to_track(suite: str, short: bool, files: str | None, overlay: Path | None) -> tuple:
    """The suite (or the user's files' trajectories and the suite they make) and the tracker's
    servos (an overlay's), or exit 2 naming what is wrong."""
    from inhand_tracker.service.bench.accuracy import files_suite, load_files

    try:
        mine = load_files([Path(p) for p in names(files) or ()])
    except ValueError as exc:
        raise fail(f"bench accuracy --{exc}") from None
    chosen = files_suite(mine) if mine else suite_named(suite, short)
    return chosen, mine, _overlay_servos(overlay, chosen.robot) if overlay else ()


def _overlay_servos(path: Path, robot: str) -> tuple:
    """The servos of a calibration overlay of ``robot``'s config, or exit 2 naming what is wrong."""
    from inhand_tracker.sim_backend import load_robot

    try:
        spec = load_robot(path)
    except ValueError as exc:
        raise fail(f"--robot-overlay: {exc}") from None
    if spec.name != robot:
        raise fail(f"--robot-overlay: '{path}' is robot '{spec.name}', the suite's is '{robot}'")
    if not spec.servos:
        raise fail(f"--robot-overlay: '{path}' has no [servos] table (write one with `calibrate`)")
    return spec.servos


@bench.command("cost-ranking")
def bench_cost_ranking(
    suite: Annotated[str, typer.Option(help=SUITE_HELP)] = "smoke",
    short: Annotated[bool, typer.Option(help="the suite in short form")] = False,
    method: Annotated[str, typer.Option(help="the optimizer that runs the population")] = "PBO",
    worlds: Annotated[int, typer.Option(help="K, worlds per track")] = 40,
    noise: Annotated[str, typer.Option(help="initial pose noise: low, med or high")] = "med",
    device: Device = "auto",
    cache: Annotated[Path | None, typer.Option(help="where generated trajectories are kept")] = None,
    json_: Json = False,
) -> None:
    """How well each cost term ranks the worlds by their true pose error (Spearman's rho)."""
    gpu_stack()
    from inhand_tracker.service.bench import ground_truth
    from inhand_tracker.service.bench.ranking import cost_ranking, format_table
    from inhand_tracker.service.paths import CACHE_DIR

    chosen = suite_named(suite, short)
    with contextlib.redirect_stdout(sys.stderr):
        by_object: dict[str, list] = {}
        for t in ground_truth(chosen, device, cache or CACHE_DIR):
            by_object.setdefault(t.object, []).append(t)
        try:
            results = {o: cost_ranking(ts, worlds, method, noise, device) for o, ts in by_object.items()}
        except ValueError as exc:
            raise fail(f"bench cost-ranking: {exc}") from None
    if json_:
        typer.echo(json.dumps({"suite": chosen.name, "method": method, "worlds": worlds, "objects": results}))
        return
    typer.echo(format_table(results, f"{chosen.name}, {method}, K={worlds}"))


@bench.command("publish")
def bench_publish(
    results: Annotated[Path, typer.Option(help="folder of result JSON files")] = Path("docs/results"),
    out: Annotated[Path, typer.Option(help="the page to write")] = Path("docs/benchmarks.md"),
) -> None:
    """docs/benchmarks.md and its charts from the results in docs/results/."""
    from inhand_tracker.service.bench.publish import render

    typer.echo(render(results, out))


@bench.command("rebuilds")
def bench_rebuilds(
    ctx: typer.Context,
    cycles: Annotated[int, typer.Option(help="populations built and dropped")] = 1000,
    worlds: Annotated[int, typer.Option(help="K of each")] = 8,
    device: Device = "auto",
    json_: Json = False,
) -> None:
    """Populations built and dropped in a loop: the service's resident and device memory before and after."""
    gpu_stack()
    from inhand_tracker.service.bench.rebuilds import as_dict, bench_rebuilds, format_table

    with _running("rebuilds"):
        result = bench_rebuilds(cycles, worlds, device)
    stamp = {"date": time.strftime("%Y-%m-%d"), "command": command_line(ctx)}
    typer.echo(json.dumps(as_dict(result) | stamp, indent=2) if json_ else format_table(result))
