"""What every command shares: the command line's Typer apps, option types and helpers."""

from __future__ import annotations

import contextlib
import gc
import re
import shlex
import sys
from enum import IntEnum
from pathlib import Path
from typing import Annotated

import typer

__all__ = [
    "Device",
    "ExitCode",
    "IntList",
    "Json",
    "app",
    "bench",
    "check_device",
    "check_folder",
    "check_listen",
    "check_port",
    "command_line",
    "endpoints",
    "fail",
    "gpu_stack",
    "names",
    "started",
    "suite_named",
]


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


def int_list(text: str | None) -> list[int] | None:
    if text is None:
        return None
    try:
        values = [int(v) for v in text.split(",") if v]
    except ValueError:
        raise typer.BadParameter(f"expected comma-separated integers, got '{text}'") from None
    if not values or min(values) < 1:
        raise typer.BadParameter(f"expected positive integers, got '{text}'")
    return values


def names(text: str | None) -> list[str] | None:
    return None if text is None else [t for t in text.split(",") if t]


def endpoints(text: str | None, option: str, command: str) -> list[str] | None:
    """Comma-separated Zenoh endpoints; one that is not (``127.0.0.1:7447`` without ``tcp/``)
    exits 2 with one line naming it and the spelling, before anything loads."""
    from inhand_tracker.client.zenoh_session import check_endpoints

    try:
        return None if text is None else check_endpoints(names(text), f"{command} --{option}")
    except ValueError as exc:
        raise fail(str(exc)) from None


IntList = Annotated[str | None, typer.Option(callback=int_list, metavar="N,N,...")]
Device = Annotated[str, typer.Option(help="auto (CUDA when present), cpu, cuda or cuda:N")]
Json = Annotated[bool, typer.Option("--json", help="print JSON instead of a table")]


def gpu_stack() -> None:
    """What every command that simulates needs first; on the robot side's light install, a clear
    word on what to install instead of an import traceback."""
    installed_stack()
    _load_frozen()
    from inhand_tracker.service.logs import quiet_warp, watch_kernel_compiles

    quiet_warp()
    watch_kernel_compiles()


def _load_frozen() -> None:
    """Import the stack once per process, out of the cycle collector's view."""
    # The stack's modules are over a million objects that live as long as the process. The cycle
    # collector, run every few hundred allocations, walks them again and again while they load, and
    # once more at exit: 4.4 of the 7.2 s that importing the service took on a 2-core CPU. They load
    # with it paused and are then frozen out of its view: a full collection while the service runs
    # then takes 17 ms there, not 0.7 s (twenty frames at 30 Hz). Loaded already (a second command
    # in one process), it is left alone: a freeze then would also keep the garbage made since.
    if "inhand_tracker.service.tracker" in sys.modules:
        return
    gc.disable()
    try:
        import inhand_tracker.sim_backend  # first: it switches off Warp's adjoints before newton is imported

        # isort: split
        import inhand_tracker.service.tracker  # noqa: F401  (torch, newton, mujoco_warp, trimesh)
    finally:
        gc.freeze()
        gc.enable()


def installed_stack() -> None:
    """Exit 2 with what to install when the service's packages are not, on the robot side's light
    install; looked up, not imported (a fraction of a second)."""
    import importlib.util

    # Looked up, not imported: newton must not be imported before forward_only_kernels.
    missing = [name for name in ("torch", "warp", "newton", "lazy_loader") if importlib.util.find_spec(name) is None]
    if missing:
        raise fail(
            f"this command simulates, and the GPU stack is not installed (missing: {', '.join(missing)}):"
            " install torch first (the CPU build: pip install torch==2.13.0 --index-url"
            " https://download.pytorch.org/whl/cpu; or your CUDA build), then"
            " pip install '.[service]' in the repository (or 'WHEEL[service]' for a built wheel)."
            " The robot side (replay, the client) needs none of them."
        )


def command_line(ctx: typer.Context) -> str:
    """The running command as a user would type it, for a result file: its options that differ
    from their defaults, read from the parsed command (sys.argv is not the command's when it is
    invoked from Python)."""
    root = ctx.find_root().command_path  # "inhand-tracker", or "python -m inhand_tracker.service.cli"
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
            if param.param_type_name == "argument":  # positional: as typed, one word each
                words += [shlex.quote(str(x)) for x in (v if isinstance(v, list) else [v])]
            elif shown != str(param.default):
                words += [param.opts[0], shlex.quote(shown)]
    return " ".join(words)


class ExitCode(IntEnum):
    """What a command's exit status says (docs/operations.md lists them)."""

    FAILED = 1
    """A failure inside the service, logged; or a replayed track that did not pass."""
    USAGE = 2
    """An option, a setting or a file's content is wrong."""
    TAKEN = 3
    """An address or port to listen on is taken."""
    FILES = 4
    """A file or folder cannot be read, made or written."""
    UNREACHABLE = 5
    """No service answered where it was looked for."""


def fail(message: str, code: int = ExitCode.USAGE) -> typer.Exit:
    """One line on stderr and the exit status ``code`` (:class:`ExitCode`)."""
    typer.echo(message, err=True)
    return typer.Exit(int(code))


def version_callback(show: bool) -> None:
    if show:
        from importlib.metadata import PackageNotFoundError, version

        from inhand_tracker.protocol import PROTOCOL_VERSION

        try:
            typer.echo(f"inhand-tracker {version('inhand-tracker')} (protocol v{PROTOCOL_VERSION})")
        except PackageNotFoundError:  # run from a source tree that was never installed
            typer.echo(f"inhand-tracker (not installed; protocol v{PROTOCOL_VERSION})")
        raise typer.Exit()


def check_device(device: str, command: str) -> None:
    """Exit 2 with one line when ``device`` is not one this machine has; Warp alone, before the
    rest of the GPU stack is imported (seconds)."""
    if device not in ("auto", "cpu") and not re.fullmatch(r"cuda(:\d+)?", device):
        raise fail(f"{command}: --device: expected auto, cpu, cuda or cuda:N, got '{device}'")
    if device.startswith("cuda"):
        from inhand_tracker.service.logs import quiet_warp

        quiet_warp()
        import warp as wp

        if not wp.is_cuda_available():
            raise fail(
                f"{command}: --device: '{device}' asked for, but this machine has no CUDA device (auto: the CPU)"
            )


def _taken_message(command: str, where: str) -> str:
    return (
        f"{command}: cannot listen on {where}: the address is taken (another service, or a Zenoh router"
        " on this host): give another with --listen tcp/127.0.0.1:PORT, or --listen '' to only --connect"
    )


def _taken(host: str, port: int) -> bool:
    """Whether a TCP ``port`` on ``host`` is taken: bound as Zenoh and the live view bind it (a port
    whose last connections linger in TIME_WAIT is free to listen on)."""
    import socket

    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((host, port))
        except OSError as exc:
            return exc.errno == 98 or "in use" in str(exc).lower()
    return False


def check_listen(endpoints: list[str], command: str) -> None:
    """Exit 3 with one line when a TCP endpoint to listen on is taken, before the GPU stack loads
    (a service on another's port would only fail once it opens its Zenoh session)."""
    for endpoint in endpoints:
        match = re.fullmatch(r"tcp/(\[[^\]]+\]|[^:]+):(\d+)", endpoint)
        if match is not None and _taken(match.group(1).strip("[]"), int(match.group(2))):
            raise fail(_taken_message(command, endpoint), ExitCode.TAKEN)


def check_port(host: str, port: int, option: str) -> None:
    """Exit 3 with one line when the live view's ``port`` on ``host`` is taken, before anything loads."""
    if _taken(host, port):
        raise fail(f"{option}: port {port} on {host} is taken (another service's view?): give another", ExitCode.TAKEN)


def check_folder(folder: Path, option: str) -> None:
    """Exit 4 with one line when ``folder`` cannot be made or written to, before anything loads: a
    recording that could not be written would otherwise fail at the first session's open."""
    import tempfile

    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=folder):
            pass
    except OSError as exc:
        raise fail(f"{option}: cannot write to '{folder}': {exc.strerror or exc}", ExitCode.FILES) from None


def check_router(connect: tuple[str, ...], command: str) -> None:
    """Exit 5 with one line when no router of a Zenoh client answers, before the GPU stack loads: a
    client cannot open without one (a peer waits for it, and says so). Only TCP-borne endpoints
    (tcp/, tls/) are knocked on, with a plain connect; others are left to Zenoh."""
    import socket

    tried = []
    for endpoint in connect:
        scheme, _, address = endpoint.partition("/")
        host, _, port = address.split("#")[0].rpartition(":")
        if scheme not in ("tcp", "tls") or not port.isdigit():
            return
        try:
            with socket.create_connection((host.strip("[]"), int(port)), timeout=0.5):
                return
        except OSError:
            tried.append(endpoint)
    if tried:
        raise fail(_no_router(command, tried), ExitCode.UNREACHABLE)


def _no_router(command: str, where: list[str]) -> str:
    return (
        f"{command}: as a Zenoh client, no router answered at {', '.join(where) or '(scouting)'}; start it"
        " first, or check the address (connect / INHAND_CONNECT)"
    )


@contextlib.contextmanager
def started(node, command: str):
    """A service node, started and closed; an address already taken exits 3, and an absent router
    of a Zenoh client 5, each with one line and the fix."""
    try:
        node.start()
    except Exception as exc:
        node.close()
        said = str(exc).lower()
        if "unable to connect to any of" in said:  # a Zenoh client needs its router at the start
            raise fail(_no_router(command, list(node.config.connect)), ExitCode.UNREACHABLE) from None
        if "address already in use" not in said:
            raise
        raise fail(_taken_message(command, ", ".join(node.config.listen)), ExitCode.TAKEN) from None
    try:
        yield node
    finally:
        node.close()


def suite_named(name: str, short: bool):
    """The benchmark suite called ``name`` (in short form), or exit 2 naming the suites there are."""
    from inhand_tracker.service.bench import SUITES

    if name not in SUITES:
        raise fail(f"--suite: expected one of {sorted(SUITES)}, got '{name}'")
    return SUITES[name].short() if short else SUITES[name]
