"""`inhand-tracker` command line."""

from __future__ import annotations

import argparse
import json
import logging
import sys

__all__ = ["forward_only_kernels", "main"]

log = logging.getLogger("inhand_tracker")


def _int_list(text: str) -> list[int]:
    try:
        values = [int(v) for v in text.split(",") if v]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got '{text}'") from None
    if not values or min(values) < 1:
        raise argparse.ArgumentTypeError(f"expected positive integers, got '{text}'")
    return values


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="inhand-tracker", description=__doc__)
    sub = p.add_subparsers(dest="command", required=True)
    bench = sub.add_parser("bench", help="benchmarks")
    bsub = bench.add_subparsers(dest="bench", required=True)
    sim = bsub.add_parser("sim", help="physics population: ms per 30 Hz frame and memory per world")
    sim.add_argument("--worlds", type=_int_list, default=[40, 256, 1024, 4096], help="K values, e.g. 40,256,1024")
    sim.add_argument("--substeps", type=_int_list, default=[8], help="substeps per frame, e.g. 4,8")
    sim.add_argument("--solver", default="auto", help="MuJoCo solvers: auto (newton), cg, newton")
    sim.add_argument("--frames", type=int, default=60, help="timed frames per K")
    sim.add_argument("--object", default="foam_brick", help="catalog object held in the grasp")
    sim.add_argument("--device", default="auto", help="auto, cpu, cuda or cuda:N")
    sim.add_argument("--json", action="store_true", help="print JSON instead of a table")

    speed = bsub.add_parser("speed", help="whole tracker frame (frame in, estimate out) against the physics alone")
    speed.add_argument("--worlds", type=_int_list, default=[40, 256, 1024, 4096, 8192], help="W, all worlds")
    speed.add_argument("--groups", type=_int_list, default=[1], help="G, sessions sharing the worlds (K = W / G)")
    speed.add_argument("--substeps", type=_int_list, default=[8], help="substeps per frame, e.g. 4,8")
    speed.add_argument(
        "--jacobian", default=None, help="constraint Jacobian layouts, e.g. dense,sparse (default: the population's)"
    )
    speed.add_argument("--frames", type=int, default=200, help="timed frames per size (after 30 warm-up frames)")
    speed.add_argument("--device", default="auto", help="auto, cpu, cuda or cuda:N")
    speed.add_argument("--json", action="store_true", help="print JSON instead of a table")

    acc = bsub.add_parser("accuracy", help="tracking accuracy (ADD) on synthetic ground truth, as the paper's IV-A")
    acc.add_argument("--suite", default="smoke", help="smoke, paper or reality-gap")
    acc.add_argument("--methods", default="OLP,EYE,WRS,REPS,PBO", help="comma-separated: OLP, EYE, WRS, REPS, PBO")
    acc.add_argument("--noise", default="low,med,high", help="initial pose noise levels: low, med, high")
    acc.add_argument("--worlds", type=int, default=40, help="K, worlds per track")
    acc.add_argument("--ablations", default="", help="comma-separated: exploration, worlds, contact, slip, or all")
    acc.add_argument(
        "--ablation-worlds",
        type=_int_list,
        default=None,
        help="K values of the worlds ablation (default 10,40,160,640,2560)",
    )
    acc.add_argument("--substeps", type=int, default=8, help="the tracker's physics substeps per frame (even)")
    acc.add_argument(
        "--repeats",
        type=int,
        default=1,
        help="independent runs of every track, batched together: each run's mean is reported (an interval)",
    )
    acc.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="a tracker or physics setting other than its default: jitter_bandwidth=0, optimizer.pbo_keep=0.25, "
        "population.impratio=30 (repeatable)",
    )
    acc.add_argument("--device", default="auto", help="auto, cpu, cuda or cuda:N")
    acc.add_argument("--out", default=None, help="output folder (default bench-results/accuracy-SUITE)")
    acc.add_argument("--cache", default=None, help="where generated trajectories are kept")
    acc.add_argument("--json", action="store_true", help="print the summary as JSON")

    pub = bsub.add_parser("publish", help="docs/benchmarks.md and its charts from the results in docs/results/")
    pub.add_argument("--results", default="docs/results", help="folder of result JSON files")
    pub.add_argument("--out", default="docs/benchmarks.md", help="the page to write")

    serve = sub.add_parser("serve", help="run the tracking service")
    serve.add_argument("--config", default=None, help="service TOML (default configs/service.toml)")
    serve.add_argument("--listen", default=None, help="Zenoh endpoints to listen on, comma-separated")
    serve.add_argument("--connect", default=None, help="Zenoh endpoints to connect to (a router), comma-separated")
    serve.add_argument("--name", default=None, help="service name: keys under inhand/v1/NAME")
    serve.add_argument("--device", default=None, help="auto, cpu, cuda or cuda:N")

    rep = sub.add_parser("replay", help="robot side: stream a trajectory file to a service and print the estimates")
    rep.add_argument("file", help="trajectory file (.traj)")
    rep.add_argument("--connect", default="tcp/127.0.0.1:7447", help="the service's endpoints, comma-separated")
    rep.add_argument("--name", default="default", help="service name")
    rep.add_argument("--method", default="PBO")
    rep.add_argument("--worlds", type=int, default=40)
    rep.add_argument("--rate", type=float, default=0.0, help="frames per second; 0: each frame after the last estimate")
    rep.add_argument("--noise", default="med", help="initial pose noise from the truth: low, med, high")

    demo = sub.add_parser(
        "demo", help="the service embedded on loopback, a bundled trajectory replayed through a client"
    )
    demo.add_argument("--device", default="auto", help="auto, cpu, cuda or cuda:N")
    demo.add_argument("--worlds", type=int, default=40)
    demo.add_argument("--method", default="PBO")
    demo.add_argument("--file", default=None, help="trajectory file (default: a bundled foam-brick pick and place)")
    return p


def _split(text: str | None) -> list[str] | None:
    return None if text is None else [t for t in text.split(",") if t]


def _serve(args: argparse.Namespace) -> int:
    import gc
    import signal
    import threading

    from service.server import TrackerNode, load_config

    try:
        config = load_config(
            args.config, listen=_split(args.listen), connect=_split(args.connect), name=args.name, device=args.device
        )
    except ValueError as exc:
        print(f"serve: {exc}", file=sys.stderr)
        return 2
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    with TrackerNode(config) as node:
        while not stop.wait(0.5) and not node.failed.is_set():
            pass
        log.info("stopping")
    if node.failed.is_set():
        return 1
    # Everything is closed; what is left is Python's final full collection, which walks every object
    # torch, warp and newton made: SIGTERM to exit took 6.8 s on a 2-core CPU, past the 5 s a
    # container gets, and 2.0 s with the heap frozen (frozen objects are not walked).
    gc.freeze()
    return 0


def _replay(args: argparse.Namespace, client=None, file: str | None = None, live: bool = False) -> int:

    import numpy as np

    from client import NOISE_LEVELS, TrackerClient, noisy_start, replay
    from protocol import Trajectory

    if args.noise not in NOISE_LEVELS:
        print(f"--noise: expected low, med or high, got '{args.noise}'", file=sys.stderr)
        return 2
    try:
        traj = Trajectory.load(file or args.file)
    except (OSError, ValueError) as exc:
        print(f"replay: {exc}", file=sys.stderr)
        return 2
    sigma_t, sigma_r = NOISE_LEVELS[args.noise]
    own = client is None
    client = client or TrackerClient(connect=_split(args.connect), service=args.name)
    try:
        p0 = noisy_start(traj, sigma_t, sigma_r)
        info = client.open_session(
            traj.robot,
            traj.object,
            p0,
            sigma_t=sigma_t,
            sigma_r=sigma_r,
            q0=traj.truth.initial_q if traj.truth else None,
            method=args.method,
            worlds=args.worlds,
        )
        print(
            f"session {info.session}: {traj.object} in {traj.robot}, {info.worlds} worlds, {info.method}; "
            f"{traj.frames} frames of '{traj.name}'",
            flush=True,
        )
        errors: list[float] = []

        def show(i: int, est) -> None:
            if traj.truth is None:
                return
            errors.append(_pose_error(traj.truth.pose[i], est.pose))
            if live and (i % 15 == 0 or i == traj.frames - 1):
                print(
                    f"\r  frame {i + 1:4d}/{traj.frames}  {est.status:10s} position error {errors[-1] * 1e3:6.1f} mm"
                    f"  latency {est.latency_ms:5.1f} ms",
                    end="",
                    flush=True,
                )

        result = replay(client, traj, rate=args.rate, on_estimate=show)
        estimates = result.estimates
        status = client.status()
        if live:
            print()
        print(f"estimates: {len(estimates)}; gaps {status.gaps}, dropped {status.duplicates + status.late}")
        print(
            f"latency, frame received to estimate ready (service): p50 {status.latency_p50_ms:.1f} ms, "
            f"p99 {status.latency_p99_ms:.1f} ms"
        )
        if result.round_trip_ms:
            rt = np.asarray(result.round_trip_ms)
            print(
                f"latency, frame put to estimate received (client): p50 {np.percentile(rt, 50):.1f} ms, "
                f"p99 {np.percentile(rt, 99):.1f} ms"
            )
        if traj.truth is not None:
            _summary(traj, estimates)
        client.close_session()
    except Exception as exc:  # a user's command: say what went wrong, no traceback
        print(f"replay: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 1
    finally:
        if own:
            client.close()
    return 0


def _pose_error(truth, pose) -> float:
    import numpy as np

    return float(np.linalg.norm(np.asarray(truth[:3]) - np.asarray(pose[:3])))


def _summary(traj, estimates) -> None:
    """ADD against the ground truth, when the object's model is at hand (the service's install)."""
    import numpy as np

    try:
        from service.evaluation import add_error
        from sim_backend import catalog_object

        points = catalog_object(traj.object).surface_points(1000)
    except (ImportError, ValueError):
        err = [_pose_error(traj.truth.pose[e.seq], e.pose) for e in estimates]
        print(f"position error: mean {np.mean(err) * 1e3:.2f} mm, max {np.max(err) * 1e3:.2f} mm")
        return
    seqs = np.array([e.seq for e in estimates])
    add = add_error(points, traj.truth.pose[seqs], np.stack([e.pose for e in estimates]))
    print(
        f"ADD over {len(add)} frames: mean {add.mean() * 1e3:.2f} mm, median {np.median(add) * 1e3:.2f} mm, "
        f"max {add.max() * 1e3:.2f} mm"
    )


def _demo(args: argparse.Namespace) -> int:
    import socket

    from client import TrackerClient
    from service.paths import DATA_DIR
    from service.server import ServiceConfig, TrackerNode

    with socket.socket() as sock:  # a free loopback port
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    endpoint = f"tcp/127.0.0.1:{port}"
    config = ServiceConfig(listen=(endpoint,), device=args.device, groups=1)  # one session: no idle groups to step
    log.info("starting the service on %s (device %s)", endpoint, args.device)
    with TrackerNode(config) as node, TrackerClient(connect=[endpoint]) as client:
        log.info("service up on %s; replaying through a client", node.device)
        args.noise, args.rate = "med", 0.0
        file = args.file or str(DATA_DIR / "smoke-foam_brick_pick_place_0.traj")
        return _replay(args, client=client, file=file, live=True)


def _speed(args: argparse.Namespace) -> int:
    import contextlib

    from service.bench.speed import as_dicts, bench_speed, format_table

    def show(r) -> None:
        print(
            f"  W={r.worlds} G={r.groups} substeps={r.substeps} {r.solver}: tracker {r.tracker_median_ms:.2f} ms "
            f"(p99 {r.tracker_p99_ms:.2f}), physics {r.physics_median_ms:.2f} ms, ratio {r.ratio:.2f}",
            file=sys.stderr,
            flush=True,
        )

    try:
        with contextlib.redirect_stdout(sys.stderr):  # Warp logs with print(); stdout is for the table or the JSON
            results = bench_speed(
                args.worlds,
                args.groups,
                args.substeps,
                frames=args.frames,
                device=args.device,
                progress=show,
                **({"jacobians": args.jacobian.split(",")} if args.jacobian else {}),
            )
    except ValueError as exc:
        print(f"bench speed: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(as_dicts(results), indent=2) if args.json else format_table(results))
    return 0


def _settings(settings: list[str]):
    """A TrackerConfig and the population's physics overrides from NAME=VALUE strings: the
    tracker's number and flag fields, its optimizer's as optimizer.NAME, and the population's
    physics numbers (impratio, tolerance, ...) as population.NAME."""
    from service.tracker import OptimizerConfig, TrackerConfig, setting_types
    from sim_backend.population import PopulationConfig

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
        flags = {"1": True, "true": True, "yes": True, "0": False, "false": False, "no": False}
        try:
            value = flags[text.lower()] if kind is bool else kind(text)
        except (KeyError, ValueError):
            raise ValueError(f"{name}: expected a value of type {kind.__name__}, got '{text}'") from None
        outer, _, inner = name.rpartition(".")
        values[outer][inner] = value
    PopulationConfig(**values["population"])  # out-of-range physics fails here, with the field named
    return TrackerConfig(optimizer=OptimizerConfig(**values["optimizer"]), **values[""]), values["population"]


def _accuracy(args: argparse.Namespace) -> int:
    import contextlib
    from pathlib import Path

    from service.bench import NOISE_LEVELS, SUITES, run_suite, write_report
    from service.paths import CACHE_DIR
    from service.tracker import METHODS

    if args.suite not in SUITES:
        print(f"--suite: expected one of {sorted(SUITES)}, got '{args.suite}'", file=sys.stderr)
        return 2
    ablations = (
        ["exploration", "worlds", "contact", "slip"]
        if args.ablations == "all"
        else [a for a in args.ablations.split(",") if a]
    )
    unknown = set(ablations) - {"exploration", "worlds", "contact", "slip"}
    if unknown:
        print(
            f"--ablations: unknown {sorted(unknown)}; expected exploration, worlds, contact, slip or all",
            file=sys.stderr,
        )
        return 2
    methods, noises = args.methods.split(","), args.noise.split(",")
    for name, values, allowed in (("--methods", methods, METHODS), ("--noise", noises, tuple(NOISE_LEVELS))):
        if not values or not set(values) <= set(allowed):
            print(f"{name}: expected some of {','.join(allowed)}, got '{','.join(values)}'", file=sys.stderr)
            return 2
    if args.substeps < 2 or args.substeps % 2:
        print(f"--substeps: expected a positive even number, got {args.substeps}", file=sys.stderr)
        return 2
    if args.repeats < 1:
        print(f"--repeats: expected >= 1, got {args.repeats}", file=sys.stderr)
        return 2
    try:
        config, population = _settings(args.set)
    except ValueError as exc:
        print(f"--set: {exc}", file=sys.stderr)
        return 2
    out = Path(args.out or f"bench-results/accuracy-{args.suite}")
    command = "inhand-tracker " + " ".join(sys.argv[1:])
    with contextlib.redirect_stdout(sys.stderr):  # Warp logs with print(); stdout is for the report or the JSON
        results = run_suite(
            SUITES[args.suite],
            methods=methods,
            noises=noises,
            worlds=args.worlds,
            ablations=ablations,
            device=args.device,
            cache=Path(args.cache) if args.cache else CACHE_DIR,
            k_ablation=args.ablation_worlds,
            checkpoint=lambda partial: write_report(partial, out, command=command + "  (partial)"),
            substeps=args.substeps,
            repeats=args.repeats,
            config=config,
            population=population,
        )
    report = write_report(results, out, command=command)
    if args.json:
        print(json.dumps({"summary": results["summary"], "ablations": results["ablations"]}, indent=2))
    else:
        print(report.read_text().split("\n## Ablation")[0].split("\n## Per trajectory")[0])
        print(f"report: {report}")
    return 0


def forward_only_kernels() -> None:
    """Have Warp compile no adjoints for the modules that do not choose (Newton's; MuJoCo-Warp's
    and ours already opt out). Nothing here differentiates through the physics, and a first start
    compiles less: the population's build and first steps on the 2-core CPU take 49 s instead of
    65, with bit-identical physics. Warp reads the setting when a kernel module is imported, so
    this runs before anything imports newton."""
    import warp as wp

    wp.config.enable_backward = False


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    from service.logs import setup_logging

    setup_logging()
    if args.command != "replay":  # the robot side's replay stays light: no warp
        from service.logs import quiet_warp, watch_kernel_compiles

        forward_only_kernels()
        quiet_warp()
        watch_kernel_compiles()
    if args.command == "bench" and args.bench == "sim":
        from service.bench.sim import as_dicts, bench_sim, format_table

        results = []
        for solver in args.solver.split(","):
            for n in args.substeps:
                results += bench_sim(
                    args.worlds, substeps=n, frames=args.frames, obj=args.object, device=args.device, solver=solver
                )
        print(json.dumps(as_dicts(results), indent=2) if args.json else format_table(results))
        return 0
    if args.command == "bench" and args.bench == "publish":
        from pathlib import Path

        from service.bench.publish import render

        print(render(Path(args.results), Path(args.out)))
        return 0
    if args.command == "bench" and args.bench == "speed":
        return _speed(args)
    if args.command == "bench" and args.bench == "accuracy":
        return _accuracy(args)
    if args.command == "serve":
        return _serve(args)
    if args.command == "replay":
        return _replay(args)
    if args.command == "demo":
        return _demo(args)
    return 2


if __name__ == "__main__":
    sys.exit(main())
