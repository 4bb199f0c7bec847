"""The service and the robot side: `serve`, `replay`, `watch`, `spec` and `demo`."""

from __future__ import annotations

import logging
import os
import sys
from pathlib import Path
from typing import Annotated

import typer

from .common import (
    Device,
    ExitCode,
    app,
    check_device,
    check_folder,
    check_listen,
    check_port,
    check_router,
    endpoints,
    fail,
    gpu_stack,
    installed_stack,
    names,
    started,
)

log = logging.getLogger("inhand_tracker")


@app.command()
def serve(
    config: Annotated[Path | None, typer.Option(help="service TOML (default configs/service.toml)")] = None,
    listen: Annotated[str | None, typer.Option(help="Zenoh endpoints to listen on, comma-separated")] = None,
    connect: Annotated[str | None, typer.Option(help="Zenoh endpoints to connect to (a router)")] = None,
    name: Annotated[str | None, typer.Option(help="service name: keys under inhand/v7/NAME")] = None,
    device: Annotated[str | None, typer.Option(help="auto, cpu, cuda or cuda:N")] = None,
    ros2: Annotated[bool | None, typer.Option("--ros2/--no-ros2", help="publish the estimates as ROS 2 topics")] = None,
    record: Annotated[Path | None, typer.Option(help="record every session to MCAP files in this folder")] = None,
    view_port: Annotated[int | None, typer.Option(help="serve a live view in a browser on this port")] = None,
) -> None:
    """Run the tracking service."""
    import gc
    import signal
    import threading

    # Before the GPU stack loads (seconds): what the command line and the environment say.
    if device is not None:
        check_device(device, "serve")
    given = listen if listen is not None else os.environ.get("INHAND_LISTEN", "tcp/127.0.0.1:7447")
    check_listen(endpoints(given, "listen", "serve"), "serve")
    endpoints(connect if connect is not None else os.environ.get("INHAND_CONNECT"), "connect", "serve")
    if view_port is not None:
        check_port("127.0.0.1", view_port, "serve --view-port")
    if record is not None:
        check_folder(record, "serve --record")
    installed_stack()
    from inhand_tracker.service.server.config import load_config  # no GPU stack: a bad value is said at once

    try:
        settings = load_config(
            config, listen=names(listen), connect=names(connect), name=name, device=device, ros2=ros2,
            record=str(record) if record else None, view_port=view_port,
        )  # fmt: skip
    except ValueError as exc:
        raise fail(f"serve: {exc}") from None
    check_device(settings.device, "serve")  # before the rest of the GPU stack loads
    if settings.view_port is not None and view_port is None:  # from the config file
        check_port(settings.view_host, settings.view_port, "serve: view_port")
    if settings.record is not None and record is None:
        check_folder(Path(settings.record), "serve: record")
    if settings.zenoh_mode == "client":
        check_router(settings.connect, "serve")
    gpu_stack()
    from inhand_tracker.service.server import TrackerNode

    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    try:
        node = TrackerNode(settings)
    except ValueError as exc:  # a robot, object or ROS 2 session the files do not hold
        raise fail(f"serve: {exc}") from None
    with started(node, "serve") as node:
        while not stop.wait(0.5) and not node.failed.is_set():
            pass
        log.info("stopping")
    # Everything is closed; what is left is Python's final full collection. The stack was frozen as it
    # loaded (gpu_stack); freezing what the service made since (its populations) spares it those too:
    # SIGTERM to exit took 0.2 s on a 2-core CPU, not 0.3-0.4, well inside the 5 s a container gets.
    gc.freeze()
    if node.failed.is_set():
        raise typer.Exit(1)


@app.command()
def settings() -> None:
    """Print the service's settings file with every setting at its default (configs/service.toml)."""
    from inhand_tracker.service.server.config import shipped_toml

    typer.echo(shipped_toml(), nl=False)


# ---------------------------------------------------------------------- the robot side
@app.command()
def replay(
    file: Annotated[Path, typer.Argument(help="a trajectory file (.traj) or a recording (folder or .mcap)")],
    connect: Annotated[str, typer.Option(help="the service's endpoints, comma-separated")] = "tcp/127.0.0.1:7447",
    name: Annotated[str, typer.Option(help="service name")] = "default",
    method: Annotated[str | None, typer.Option(help="OLP, EYE, WRS, REPS or PBO (default: the protocol's)")] = None,
    worlds: Annotated[
        int | None, typer.Option(help="K (default: auto, the most the service's frame budget allows)")
    ] = None,
    rate: Annotated[float, typer.Option(help="frames per second; 0: each frame after the last estimate")] = 0.0,
    noise: Annotated[str, typer.Option(help="initial pose noise from the truth: low, med, high")] = "med",
    allow_fewer: Annotated[bool, typer.Option(help="take fewer than --worlds where the budget is short")] = False,
    service_key: Annotated[str | None, typer.Option(help="the key fingerprint `serve` prints: checked")] = None,
) -> None:
    """Robot side: stream a trajectory file to a service and print the estimates. FILE may name
    a bundled trajectory (`smoke-foam_brick_pick_place_0`) from anywhere."""
    from inhand_tracker.client import TrackerClient
    from inhand_tracker.client.report import replay_file

    file = _bundled(file)
    where = endpoints(connect, "connect", "replay")
    with TrackerClient(connect=where, service=name, service_key=service_key) as client:
        try:
            live = sys.stdout.isatty()  # a terminal gets one line rewritten; a log a line every 10 s
            code = replay_file(
                client, file, method, worlds, rate, noise, live, say=typer.echo, score=_catalog_add,
                allow_fewer=allow_fewer,
            )  # fmt: skip
        except ValueError as exc:
            raise fail(str(exc)) from None
    raise typer.Exit(code)


def _bundled(file: Path) -> Path:
    """``file``, or the bundled trajectory it names (with or without ``.traj``); exit 4 naming them."""
    from inhand_tracker.service.paths import DATA_DIR  # paths only: the robot side's install has it

    if file.exists():
        return file
    for candidate in (DATA_DIR / file.name, DATA_DIR / f"{file.name}.traj"):
        if candidate.is_file():
            return candidate
    names = ", ".join(sorted(p.stem for p in DATA_DIR.glob("*.traj")))
    raise fail(f"replay: no such file '{file}', nor a bundled trajectory of that name ({names})", ExitCode.FILES)


def _catalog_add(name: str, true_pose, est_pose):
    """ADD over the catalog's object where the service is installed (imported after the replay,
    not before it); a ValueError on the robot side alone, whose report then gives the position error."""
    try:
        from inhand_tracker.service.evaluation import catalog_add
    except ImportError:  # the light install: no torch, no object catalog
        raise ValueError("the service is not installed") from None
    return catalog_add(name, true_pose, est_pose)


@app.command()
def watch(
    connect: Annotated[str, typer.Option(help="the service's endpoints, comma-separated")] = "tcp/127.0.0.1:7447",
    name: Annotated[str, typer.Option(help="service name")] = "default",
    count: Annotated[int, typer.Option(help="stop after this many estimates (0: until Ctrl-C)")] = 0,
) -> None:
    """Robot side: print every session's estimates as the service publishes them."""
    import threading

    from inhand_tracker.client import TrackerClient

    seen, done = [0], threading.Event()

    def show(e) -> None:
        x, y, z = e.pose[:3]
        typer.echo(f"{e.session} seq {e.seq}: ({x:+.3f}, {y:+.3f}, {z:+.3f}) m  {e.status}")
        seen[0] += 1
        if count and seen[0] >= count:
            done.set()

    with TrackerClient(connect=endpoints(connect, "connect", "watch"), service=name) as client:
        try:
            client.wait_ready(timeout=3600, absent=3.0)  # a service that is not there is said within seconds
        except TimeoutError as exc:
            raise fail(f"watch: {exc}", ExitCode.UNREACHABLE) from None
        watcher = client.watch(show)
        typer.echo(f"watching service '{name}'")
        try:
            done.wait()
        except KeyboardInterrupt:
            pass
        watcher.undeclare()


@app.command("robot-key")
def robot_key(
    file: Annotated[Path, typer.Argument(help="the robot's key file (made there if it does not exist)")],
) -> None:
    """A robot's own key: its fingerprint, for the service's robot_keys (TrackerClient(identity=FILE))."""
    from inhand_tracker.protocol.identity import RobotKey

    try:
        key = RobotKey.load_or_create(file)
    except (OSError, ValueError) as exc:
        raise fail(f"robot-key: {exc}", ExitCode.FILES) from None
    typer.echo(key.fingerprint)


@app.command()
def spec(
    out: Annotated[Path, typer.Option(help="folder to write to")] = Path("docs/protocol"),
) -> None:
    """The wire spec for other languages: every message's JSON Schema and field table, and golden
    payloads (msgpack beside the values they carry)."""
    from inhand_tracker.protocol.spec import write_spec

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

    from inhand_tracker.protocol import METHODS
    from inhand_tracker.service.paths import DATA_DIR

    # Everything a user can get wrong is checked before the GPU stack loads and the service starts.
    if method is not None and method not in METHODS:
        raise fail(f"demo: --method: expected one of {', '.join(METHODS)}, got '{method}'")
    file = file or DATA_DIR / "smoke-foam_brick_pick_place_0.traj"
    if not file.is_file():
        raise fail(f"demo: --file: no such file '{file}'", ExitCode.FILES)
    check_device(device, "demo")
    if record is not None:
        check_folder(record, "demo --record")
    gpu_stack()
    from inhand_tracker.client import TrackerClient
    from inhand_tracker.client.report import replay_file
    from inhand_tracker.service.server import ServiceConfig, TrackerNode

    with socket.socket() as sock:  # a free loopback port
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    endpoint = f"tcp/127.0.0.1:{port}"
    # One session: no idle groups to step. No frame budget: the replay goes as fast as it can.
    config = ServiceConfig(
        listen=(endpoint,), device=device, groups=1, rate_hz=0, record=str(record) if record else None
    )
    log.info("starting the service on %s (device %s)", endpoint, device)
    node = TrackerNode(config)
    key = node.manager.identity.fingerprint  # the embedded service's: the demo checks what answers
    with started(node, "demo"), TrackerClient(connect=[endpoint], service_key=key) as client:
        # The embedded service compiles its kernels first: minutes on a cold cache and a small CPU,
        # with a progress line meanwhile. This client waits for it however long that takes.
        client.wait_ready(timeout=3600)
        log.info("service up on %s; replaying through a client", node.device)
        try:
            code = replay_file(client, file, method, worlds, live=True, say=typer.echo, score=_catalog_add)
        except ValueError as exc:
            raise fail(str(exc)) from None
        raise typer.Exit(code)
