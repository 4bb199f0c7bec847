"""`inhand-tracker`: the tracking service, the robot side's replay, the demo and the benchmarks.

Heavy imports (torch, warp, newton) happen inside the commands that need them, so `replay` and
`--help` stay light. Defaults live in the settings they belong to (ServiceConfig,
PopulationConfig, TrackerConfig, the protocol); an option left out takes that default.
"""

from __future__ import annotations

import contextlib
import json
import logging
import shlex
import sys
import time
from pathlib import Path
from typing import Annotated

import typer

__all__ = ["app", "forward_only_kernels", "main"]

log = logging.getLogger("inhand_tracker")

app = typer.Typer(
    name="inhand-tracker",
    help="Track an object held in a robot hand from the robot's commands and touch, with GPU physics.",
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,  # plain errors: one line a log or a test can read
)
bench = typer.Typer(
    help="Benchmarks: accuracy, speed, the physics alone, and the docs page.",
    no_args_is_help=True,
    rich_markup_mode=None,
)
app.add_typer(bench, name="bench")


def _int_list(text: str | None) -> list[int] | None:
    if text is None:
        return None
    try:
        values = [int(v) for v in text.split(",") if v]
    except ValueError:
        raise typer.BadParameter(f"expected comma-separated integers, got '{text}'") from None
    if not values or min(values) < 1:
        raise typer.BadParameter(f"expected positive integers, got '{text}'")
    return values


def _names(text: str | None) -> list[str] | None:
    return None if text is None else [t for t in text.split(",") if t]


IntList = Annotated[str | None, typer.Option(callback=_int_list, metavar="N,N,...")]
Device = Annotated[str, typer.Option(help="auto (CUDA when present), cpu, cuda or cuda:N")]
Json = Annotated[bool, typer.Option("--json", help="print JSON instead of a table")]


def forward_only_kernels() -> None:
    """Have Warp compile no adjoints for the modules that do not choose (Newton's; MuJoCo-Warp's
    and ours already opt out). Nothing here differentiates through the physics, and a first start
    compiles about a quarter less, with bit-identical physics. Warp reads the setting when a
    kernel module is imported, so this runs before anything imports newton."""
    import warp as wp

    wp.config.enable_backward = False


def _gpu_stack() -> None:
    """What every command that simulates needs first; on the robot side's light install, a clear
    word on what to install instead of an import traceback."""
    import importlib.util

    # Looked up, not imported: newton must not be imported before forward_only_kernels.
    missing = [name for name in ("torch", "warp", "newton") if importlib.util.find_spec(name) is None]
    if missing:
        raise _fail(
            f"this command simulates, and the GPU stack is not installed (missing: {', '.join(missing)}):"
            " install torch first (pip install torch==2.13.0 for the CPU build, or your CUDA build), then"
            " pip install 'inhand-tracker[service]'. The robot side (replay, the client) needs neither."
        )
    from service.logs import quiet_warp, watch_kernel_compiles

    forward_only_kernels()
    quiet_warp()
    watch_kernel_compiles()


def _command_line(ctx: typer.Context) -> str:
    """The running command as a user would type it, for a result file: its options that differ
    from their defaults, read from the parsed command (sys.argv is not the command's when it is
    invoked from Python)."""
    root = ctx.find_root().command_path  # "inhand-tracker", or "python -m service.cli"
    words = ["inhand-tracker", *ctx.command_path[len(root) :].split()]
    for param in ctx.command.params:
        value = ctx.params.get(param.name)
        if value is None or value == () or param.name == "json_":
            continue
        if isinstance(value, bool):
            if value != param.default:
                words.append(param.opts[0] if value else param.secondary_opts[0])
            continue
        repeated = isinstance(value, tuple) or getattr(param, "multiple", False)  # e.g. --set, once per value
        for v in value if repeated else (value,):
            shown = ",".join(map(str, v)) if isinstance(v, list) else str(v)
            if shown != str(param.default):
                words += [param.opts[0], shlex.quote(shown)]
    return " ".join(words)


def _fail(message: str, code: int = 2) -> typer.Exit:
    typer.echo(message, err=True)
    return typer.Exit(code)


def _version(show: bool) -> None:
    if show:
        from importlib.metadata import PackageNotFoundError, version

        from protocol import PROTOCOL_VERSION

        try:
            typer.echo(f"inhand-tracker {version('inhand-tracker')} (protocol v{PROTOCOL_VERSION})")
        except PackageNotFoundError:  # run from a source tree that was never installed
            typer.echo(f"inhand-tracker (not installed; protocol v{PROTOCOL_VERSION})")
        raise typer.Exit()


@app.callback()
def _main(
    version: Annotated[
        bool, typer.Option("--version", callback=_version, is_eager=True, help="print the version and exit")
    ] = False,
) -> None:
    from service.logs import setup_logging

    setup_logging()


# ---------------------------------------------------------------------- the service
@app.command()
def serve(
    config: Annotated[Path | None, typer.Option(help="service TOML (default configs/service.toml)")] = None,
    listen: Annotated[str | None, typer.Option(help="Zenoh endpoints to listen on, comma-separated")] = None,
    connect: Annotated[str | None, typer.Option(help="Zenoh endpoints to connect to (a router)")] = None,
    name: Annotated[str | None, typer.Option(help="service name: keys under inhand/v3/NAME")] = None,
    device: Annotated[str | None, typer.Option(help="auto, cpu, cuda or cuda:N")] = None,
    ros2: Annotated[bool | None, typer.Option("--ros2/--no-ros2", help="publish the estimates as ROS 2 topics")] = None,
    record: Annotated[Path | None, typer.Option(help="record every session to MCAP files in this folder")] = None,
    view_port: Annotated[int | None, typer.Option(help="serve a live view in a browser on this port")] = None,
) -> None:
    """Run the tracking service."""
    import gc
    import signal
    import threading

    _gpu_stack()
    from service.server import TrackerNode, load_config

    try:
        settings = load_config(
            config, listen=_names(listen), connect=_names(connect), name=name, device=device, ros2=ros2,
            record=str(record) if record else None, view_port=view_port,
        )  # fmt: skip
    except ValueError as exc:
        raise _fail(f"serve: {exc}") from None
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    with TrackerNode(settings) as node:
        while not stop.wait(0.5) and not node.failed.is_set():
            pass
        log.info("stopping")
    # Everything is closed; what is left is Python's final full collection, which walks every object
    # torch, warp and newton made: SIGTERM to exit took 6.8 s on a 2-core CPU, past the 5 s a
    # container gets, and 2.0 s with the heap frozen (frozen objects are not walked).
    gc.freeze()
    if node.failed.is_set():
        raise typer.Exit(1)


# ---------------------------------------------------------------------- the robot side
@app.command()
def replay(
    file: Annotated[Path, typer.Argument(help="a trajectory file (.traj) or a session recording (.mcap)")],
    connect: Annotated[str, typer.Option(help="the service's endpoints, comma-separated")] = "tcp/127.0.0.1:7447",
    name: Annotated[str, typer.Option(help="service name")] = "default",
    method: Annotated[str | None, typer.Option(help="OLP, EYE, WRS, REPS or PBO (default: the protocol's)")] = None,
    worlds: Annotated[
        int | None, typer.Option(help="K (default: auto, the most the service's frame budget allows)")
    ] = None,
    rate: Annotated[float, typer.Option(help="frames per second; 0: each frame after the last estimate")] = 0.0,
    noise: Annotated[str, typer.Option(help="initial pose noise from the truth: low, med, high")] = "med",
) -> None:
    """Robot side: stream a trajectory file to a service and print the estimates."""
    from client import TrackerClient

    with TrackerClient(connect=_names(connect), service=name) as client:
        code = _replay(client, file, method, worlds, rate, noise, live=False)
    raise typer.Exit(code)


@app.command()
def watch(
    connect: Annotated[str, typer.Option(help="the service's endpoints, comma-separated")] = "tcp/127.0.0.1:7447",
    name: Annotated[str, typer.Option(help="service name")] = "default",
    count: Annotated[int, typer.Option(help="stop after this many estimates (0: until Ctrl-C)")] = 0,
) -> None:
    """Robot side: print every session's estimates as the service publishes them."""
    import threading

    from client import TrackerClient

    seen, done = [0], threading.Event()

    def show(e) -> None:
        x, y, z = e.pose[:3]
        typer.echo(f"{e.session} seq {e.seq}: ({x:+.3f}, {y:+.3f}, {z:+.3f}) m  {e.status}")
        seen[0] += 1
        if count and seen[0] >= count:
            done.set()

    with TrackerClient(connect=_names(connect), service=name) as client:
        watcher = client.watch(show)
        typer.echo(f"watching service '{name}'")
        try:
            done.wait()
        except KeyboardInterrupt:
            pass
        watcher.undeclare()


def _replay(client, file: Path, method: str | None, worlds: int | None, rate: float, noise: str, live: bool) -> int:
    import numpy as np

    from client import NOISE_LEVELS, noisy_start
    from client import replay as stream
    from protocol import SessionRecording, Trajectory

    if noise not in NOISE_LEVELS:
        raise _fail(f"--noise: expected low, med or high, got '{noise}'")
    recording = None
    try:
        if file.suffix == ".mcap":
            recording = SessionRecording.load(file)
            traj = recording.trajectory
        else:
            traj = Trajectory.load(file)
    except (OSError, ValueError) as exc:
        raise _fail(f"replay: {exc}") from None
    chosen = {k: v for k, v in {"method": method, "worlds": worlds}.items() if v is not None}
    if recording is not None:  # the session as it was opened, unless told otherwise
        o = recording.opened
        start = {"p0": o["p0"], "sigma_t": o["sigma_t"], "sigma_r": o["sigma_r"], "q0": o["q0"]}
        chosen = {"method": o["method"], "worlds": o["worlds"], "overrides": o["overrides"], **chosen}
    else:
        sigma_t, sigma_r = NOISE_LEVELS[noise]
        start = {"p0": noisy_start(traj, sigma_t, sigma_r), "sigma_t": sigma_t, "sigma_r": sigma_r}
        start["q0"] = traj.truth.initial_q if traj.truth else None
    try:
        info = client.open_session(traj.robot, traj.object, **start, **chosen)
        typer.echo(
            f"session {info.session}: {traj.object} in {traj.robot}, {info.worlds} worlds, {info.method}; "
            f"{traj.frames} frames of '{traj.name}'"
        )
        errors: list[float] = []

        def show(i: int, est) -> None:
            if traj.truth is None:
                return
            errors.append(float(np.linalg.norm(traj.truth.pose[i, :3] - est.pose[:3])))
            if live and (i % 15 == 0 or i == traj.frames - 1):
                print(
                    f"\r  frame {i + 1:4d}/{traj.frames}  {est.status:10s} position error {errors[-1] * 1e3:6.1f} mm"
                    f"  latency {est.latency_ms:5.1f} ms",
                    end="",
                    flush=True,
                )

        result = stream(client, traj, rate=rate, on_estimate=show)
        status = client.status()
        if live:
            print()
        typer.echo(f"estimates: {len(result.estimates)}; gaps {status.gaps}, dropped {status.duplicates + status.late}")
        typer.echo(
            f"latency, frame received to estimate ready (service): p50 {status.latency_p50_ms:.1f} ms, "
            f"p99 {status.latency_p99_ms:.1f} ms"
        )
        if result.round_trip_ms:
            rt = np.asarray(result.round_trip_ms)
            typer.echo(
                f"latency, frame put to estimate received (client): p50 {np.percentile(rt, 50):.1f} ms, "
                f"p99 {np.percentile(rt, 99):.1f} ms"
            )
        if traj.truth is not None:
            _summary(traj, result.estimates)
        if recording is not None and recording.estimates:
            was = {e.seq: e.pose[:3] for e in recording.estimates}
            moved = [float(np.linalg.norm(e.pose[:3] - was[e.seq])) for e in result.estimates if e.seq in was]
            most = max(moved, default=0.0) * 1e3
            typer.echo(f"against the recording: {len(moved)} estimates, position differs by at most {most:.3f} mm")
        client.close_session()
    except Exception as exc:  # a user's command: say what went wrong, no traceback
        typer.echo(f"replay: {type(exc).__name__}: {exc}", err=True)
        return 1
    return 0


def _summary(traj, estimates) -> None:
    """ADD against the ground truth, when the object's model is at hand (the service's install)."""
    import numpy as np

    try:
        from service.evaluation import add_error
        from sim_backend import catalog_object

        points = catalog_object(traj.object).surface_points(1000)
    except (ImportError, ValueError):
        err = [float(np.linalg.norm(traj.truth.pose[e.seq, :3] - e.pose[:3])) for e in estimates]
        typer.echo(f"position error: mean {np.mean(err) * 1e3:.2f} mm, max {np.max(err) * 1e3:.2f} mm")
        return
    seqs = np.array([e.seq for e in estimates])
    add = add_error(points, traj.truth.pose[seqs], np.stack([e.pose for e in estimates]))
    typer.echo(
        f"ADD over {len(add)} frames: mean {add.mean() * 1e3:.2f} mm, median {np.median(add) * 1e3:.2f} mm, "
        f"max {add.max() * 1e3:.2f} mm"
    )


@app.command()
def spec(
    out: Annotated[Path, typer.Option(help="folder to write to")] = Path("docs/protocol"),
) -> None:
    """The wire spec for other languages: every message's JSON Schema and field table, and golden
    payloads (msgpack beside the values they carry)."""
    from protocol.spec import write_spec

    written = write_spec(out)
    typer.echo(f"wrote {len(written)} files under {out}")


@app.command()
def demo(
    device: Device = "auto",
    worlds: Annotated[int | None, typer.Option(help="K (default: the paper's 40)")] = None,
    method: Annotated[str | None, typer.Option(help="OLP, EYE, WRS, REPS or PBO (default: the protocol's)")] = None,
    file: Annotated[Path | None, typer.Option(help="trajectory (default: a bundled foam-brick pick and place)")] = None,
    record: Annotated[Path | None, typer.Option(help="record the session to an MCAP file in this folder")] = None,
) -> None:
    """The service embedded on loopback, a bundled trajectory replayed through a client."""
    import socket

    _gpu_stack()
    from client import TrackerClient
    from service.paths import DATA_DIR
    from service.server import ServiceConfig, TrackerNode

    with socket.socket() as sock:  # a free loopback port
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    endpoint = f"tcp/127.0.0.1:{port}"
    # One session: no idle groups to step. No frame budget: the replay goes as fast as it can.
    config = ServiceConfig(
        listen=(endpoint,), device=device, groups=1, rate_hz=0, record=str(record) if record else None
    )
    log.info("starting the service on %s (device %s)", endpoint, device)
    with TrackerNode(config) as node, TrackerClient(connect=[endpoint]) as client:
        # The embedded service compiles its kernels first: minutes on a cold cache and a small CPU,
        # with a progress line meanwhile. This client waits for it however long that takes.
        client.wait_ready(timeout=3600)
        log.info("service up on %s; replaying through a client", node.device)
        file = file or DATA_DIR / "smoke-foam_brick_pick_place_0.traj"
        raise typer.Exit(_replay(client, file, method, worlds, 0.0, "med", live=True))


# ---------------------------------------------------------------------- benchmarks
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
    _gpu_stack()
    from service.bench.sim import as_dicts, bench_sim
    from service.bench.sim import format_table as table
    from sim_backend import PopulationConfig

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
    _gpu_stack()
    from service.bench.speed import as_dicts, bench_speed, format_table
    from service.server.budget import device_name
    from service.tracker import TrackerConfig
    from sim_backend import PopulationConfig, resolve_device

    try:
        solver_caps = [(None, None) if c == "default" else tuple(int(v) for v in c.split("x")) for c in _names(caps)]
        if any(len(c) != 2 for c in solver_caps):
            raise ValueError
    except ValueError:
        text = f"bench speed: caps: expected ITERATIONSxLINE_SEARCH or default, comma-separated, got {caps!r}"
        raise _fail(text) from None
    try:
        config, physics = _settings(set_ or [])
        if config != TrackerConfig():
            raise ValueError(f"expected population.NAME=VALUE (the physics), got {set_}")
    except ValueError as exc:
        raise _fail(f"bench speed: --set: {exc}") from None

    def show(r) -> None:
        log.info(
            "W=%d G=%d substeps=%d %s: tracker %.2f ms (p99 %.2f), physics %.2f ms, ratio %.2f",
            r.worlds, r.groups, r.substeps, r.solver, r.tracker_median_ms, r.tracker_p99_ms,
            r.physics_median_ms, r.ratio,
        )  # fmt: skip

    try:
        with contextlib.redirect_stdout(sys.stderr):  # anything a library prints; stdout is for the table or JSON
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
    except ValueError as exc:
        raise _fail(f"bench speed: {exc}") from None
    if json_:
        head = {"device": device_name(resolve_device(device)), "date": time.strftime("%Y-%m-%d")}
        head["command"] = _command_line(ctx)
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
    device: Device = "auto",
    json_: Json = False,
) -> None:
    """The service under load: N robots at a fixed rate; estimates per second, latency, late frames."""
    _gpu_stack()
    from service.bench.load import as_dicts, bench_load, format_table

    try:
        with contextlib.redirect_stdout(sys.stderr):
            results = bench_load(sessions, worlds, rate, seconds, device, connect=tuple(_names(connect)))
    except ValueError as exc:
        raise _fail(f"bench load: {exc}") from None
    typer.echo(json.dumps(as_dicts(results), indent=2) if json_ else format_table(results))


def _suite(name: str, short: bool):
    """The benchmark suite called ``name`` (in short form), or exit 2 naming the suites there are."""
    from service.bench import SUITES

    if name not in SUITES:
        raise _fail(f"--suite: expected one of {sorted(SUITES)}, got '{name}'")
    return SUITES[name].short() if short else SUITES[name]


def _settings(settings: list[str]):
    """A TrackerConfig and the population's physics overrides from NAME=VALUE strings: the
    tracker's number and flag fields, its optimizer's as optimizer.NAME, and the population's
    physics numbers (impratio, tolerance, ...) as population.NAME. Values are parsed by pydantic,
    as the service's settings are."""
    from pydantic import TypeAdapter, ValidationError

    from service.tracker import OptimizerConfig, TrackerConfig, setting_types
    from sim_backend import PopulationConfig

    kinds = (int, float, bool)
    # Layout, rate and seeds have their own flags or belong to the suite.
    own = {"seed", "groups", "worlds", "substeps", "frame_rate"}
    top = {k: t for k, t in setting_types(TrackerConfig, kinds).items() if k not in own}
    nested = {f"optimizer.{k}": t for k, t in setting_types(OptimizerConfig, kinds).items()}
    nested |= {f"population.{k}": t for k, t in setting_types(PopulationConfig, kinds).items() if k not in own}
    values: dict[str, dict] = {"": {}, "optimizer": {}, "population": {}}
    for item in settings:
        name, sep, text = item.partition("=")
        kind = top.get(name) or nested.get(name)
        if not sep or kind is None:
            raise ValueError(f"expected NAME=VALUE with NAME one of {sorted(top) + sorted(nested)}, got '{item}'")
        try:
            value = TypeAdapter(kind).validate_python(text)
        except ValidationError:
            raise ValueError(f"{name}: expected a value of type {kind.__name__}, got '{text}'") from None
        outer, _, inner = name.rpartition(".")
        values[outer][inner] = value
    PopulationConfig(**values["population"])  # out-of-range physics fails here, with the field named
    return TrackerConfig(optimizer=OptimizerConfig(**values["optimizer"]), **values[""]), values["population"]


@bench.command("accuracy")
def bench_accuracy(
    ctx: typer.Context,
    suite: Annotated[str, typer.Option(help="smoke, paper, reality-gap, cross-engine (+ -shadow) or loss")] = "smoke",
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
    device: Device = "auto",
    out: Annotated[Path | None, typer.Option(help="output folder (default bench-results/accuracy-SUITE)")] = None,
    cache: Annotated[Path | None, typer.Option(help="where generated trajectories are kept")] = None,
    save_frames: Annotated[
        bool, typer.Option(help="also write frames.npz: each frame's error, reported covariance and cost")
    ] = False,
    json_: Json = False,
) -> None:
    """Tracking accuracy (ADD) on synthetic ground truth, as the paper's IV-A."""
    _gpu_stack()
    from service.bench import run_suite, write_report
    from service.paths import CACHE_DIR

    picked = _suite(suite, short)
    studies = ["exploration", "worlds", "contact", "slip"] if ablations == "all" else _names(ablations)
    try:
        config, population = _settings(set_ or [])
    except ValueError as exc:
        raise _fail(f"--set: {exc}") from None
    try:
        sigma_t, sigma_r = (float(v) for v in vision_sigma.split(","))
    except ValueError:
        raise _fail(f"bench accuracy: vision-sigma: expected POSITION,ROTATION, got {vision_sigma!r}") from None
    out = out or Path(f"bench-results/accuracy-{suite}")
    command = _command_line(ctx)
    chosen = {k: v for k, v in {"worlds": worlds, "substeps": substeps, "k_ablation": ablation_worlds}.items() if v}
    try:
        with contextlib.redirect_stdout(sys.stderr):  # anything a library prints; stdout is for the report or JSON
            results = run_suite(
                picked,
                methods=_names(methods),
                noises=_names(noise),
                ablations=studies,
                device=device,
                cache=cache or CACHE_DIR,
                checkpoint=lambda partial: write_report(partial, out, command=command + "  (partial)"),
                repeats=repeats,
                config=config,
                population=population,
                observations=observations,
                vision_sigma=(sigma_t, sigma_r),
                frames_to=out / "frames.npz" if save_frames else None,
                **chosen,
            )
    except ValueError as exc:
        raise _fail(f"bench accuracy: {exc}") from None
    report = write_report(results, out, command=command)
    if json_:
        typer.echo(json.dumps({"summary": results["summary"], "ablations": results["ablations"]}, indent=2))
    else:
        typer.echo(report.read_text().split("\n## Ablation")[0].split("\n## Per trajectory")[0])
        typer.echo(f"report: {report}")


@bench.command("cost-ranking")
def bench_cost_ranking(
    suite: Annotated[str, typer.Option(help="smoke, paper, reality-gap, cross-engine (+ -shadow) or loss")] = "smoke",
    short: Annotated[bool, typer.Option(help="the suite in short form")] = False,
    method: Annotated[str, typer.Option(help="the optimizer that runs the population")] = "PBO",
    worlds: Annotated[int, typer.Option(help="K, worlds per track")] = 40,
    noise: Annotated[str, typer.Option(help="initial pose noise: low, med or high")] = "med",
    device: Device = "auto",
    cache: Annotated[Path | None, typer.Option(help="where generated trajectories are kept")] = None,
    json_: Json = False,
) -> None:
    """How well each cost term ranks the worlds by their true pose error (Spearman's rho)."""
    _gpu_stack()
    from service.bench import ground_truth
    from service.bench.ranking import cost_ranking
    from service.paths import CACHE_DIR

    chosen = _suite(suite, short)
    with contextlib.redirect_stdout(sys.stderr):
        by_object: dict[str, list] = {}
        for t in ground_truth(chosen, device, cache or CACHE_DIR):
            by_object.setdefault(t.object, []).append(t)
        try:
            results = {o: cost_ranking(ts, worlds, method, noise, device) for o, ts in by_object.items()}
        except ValueError as exc:
            raise _fail(f"bench cost-ranking: {exc}") from None
    if json_:
        typer.echo(json.dumps({"suite": chosen.name, "method": method, "worlds": worlds, "objects": results}))
        return
    objects = list(results)
    typer.echo(f"Spearman rho of cost against true ADD over each group's worlds ({chosen.name}, {method}, K={worlds})")
    typer.echo(f"{'term':<18}" + "".join(f"{o:>22}" for o in objects))
    for term in next(iter(results.values())):
        cells = []
        for o in objects:
            r = results[o][term]
            cells.append("-" if r["rho"] is None else f"{r['rho']:+.2f} ({100 * r['defined']:.0f} %)")
        typer.echo(f"{term:<18}" + "".join(f"{c:>22}" for c in cells))


@bench.command("publish")
def bench_publish(
    results: Annotated[Path, typer.Option(help="folder of result JSON files")] = Path("docs/results"),
    out: Annotated[Path, typer.Option(help="the page to write")] = Path("docs/benchmarks.md"),
) -> None:
    """docs/benchmarks.md and its charts from the results in docs/results/."""
    from service.bench.publish import render

    typer.echo(render(results, out))


def main(argv: list[str] | None = None) -> int:
    """Run the command line; returns the exit status (2 for a bad argument, with the reason)."""
    try:
        app(args=argv)
    except SystemExit as exc:
        return exc.code if isinstance(exc.code, int) else int(exc.code is not None)
    return 0


if __name__ == "__main__":
    sys.exit(main())
