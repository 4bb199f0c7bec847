"""`inhand-tracker` command line."""

from __future__ import annotations

import argparse
import json
import sys

__all__ = ["main"]


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
    sim.add_argument("--solver", default="auto", help="MuJoCo solvers: auto (newton on CUDA, cg on CPU), cg, newton")
    sim.add_argument("--frames", type=int, default=60, help="timed frames per K")
    sim.add_argument("--object", default="foam_brick", help="catalog object held in the grasp")
    sim.add_argument("--device", default="auto", help="auto, cpu, cuda or cuda:N")
    sim.add_argument("--json", action="store_true", help="print JSON instead of a table")

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
    acc.add_argument("--device", default="auto", help="auto, cpu, cuda or cuda:N")
    acc.add_argument("--out", default=None, help="output folder (default bench-results/accuracy-SUITE)")
    acc.add_argument("--cache", default=None, help="where generated trajectories are kept")
    acc.add_argument("--json", action="store_true", help="print the summary as JSON")
    return p


def _accuracy(args: argparse.Namespace) -> int:
    from pathlib import Path

    import warp as wp

    from service.accuracy import CACHE_DIR, NOISE_LEVELS, SUITES, run_suite
    from service.optimizers import METHODS
    from service.report import write_report

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
    wp.config.quiet = True  # Warp's kernel-cache log goes to stdout, where the report or the JSON goes
    results = run_suite(
        SUITES[args.suite],
        methods=methods,
        noises=noises,
        worlds=args.worlds,
        ablations=ablations,
        device=args.device,
        cache=Path(args.cache) if args.cache else CACHE_DIR,
    )
    out = Path(args.out or f"bench-results/accuracy-{args.suite}")
    report = write_report(results, out, command="inhand-tracker " + " ".join(sys.argv[1:]))
    if args.json:
        print(json.dumps({"summary": results["summary"], "ablations": results["ablations"]}, indent=2))
    else:
        print(report.read_text().split("\n## Ablation")[0].split("\n## Per trajectory")[0])
        print(f"report: {report}")
    return 0


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    if args.command == "bench" and args.bench == "sim":
        from sim_backend.bench import as_dicts, bench_sim, format_table

        results = []
        for solver in args.solver.split(","):
            for n in args.substeps:
                results += bench_sim(
                    args.worlds, substeps=n, frames=args.frames, obj=args.object, device=args.device, solver=solver
                )
        print(json.dumps(as_dicts(results), indent=2) if args.json else format_table(results))
        return 0
    if args.command == "bench" and args.bench == "accuracy":
        return _accuracy(args)
    return 2


if __name__ == "__main__":
    sys.exit(main())
