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
    bsub = bench.add_subparsers(dest="suite", required=True)
    sim = bsub.add_parser("sim", help="physics population: ms per 30 Hz frame and memory per world")
    sim.add_argument("--worlds", type=_int_list, default=[40, 256, 1024, 4096], help="K values, e.g. 40,256,1024")
    sim.add_argument("--substeps", type=_int_list, default=[8], help="substeps per frame, e.g. 4,8")
    sim.add_argument("--solver", default="auto", help="MuJoCo solvers: auto (newton on CUDA, cg on CPU), cg, newton")
    sim.add_argument("--frames", type=int, default=60, help="timed frames per K")
    sim.add_argument("--object", default="foam_brick", help="catalog object held in the grasp")
    sim.add_argument("--device", default="auto", help="auto, cpu, cuda or cuda:N")
    sim.add_argument("--json", action="store_true", help="print JSON instead of a table")
    return p


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    if args.command == "bench" and args.suite == "sim":
        from sim_backend.bench import as_dicts, bench_sim, format_table

        results = []
        for solver in args.solver.split(","):
            for n in args.substeps:
                results += bench_sim(
                    args.worlds, substeps=n, frames=args.frames, obj=args.object, device=args.device, solver=solver
                )
        print(json.dumps(as_dicts(results), indent=2) if args.json else format_table(results))
        return 0
    return 2


if __name__ == "__main__":
    sys.exit(main())
