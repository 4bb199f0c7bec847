"""Watch the estimates of every session of a tracking service (a dashboard, a logger).

python examples/pose_watcher.py --connect tcp/127.0.0.1:7447 --count 20
"""

from __future__ import annotations

import argparse
import threading

from inhand_tracker.client import TrackerClient
from inhand_tracker.protocol import Estimate


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--connect", default="tcp/127.0.0.1:7447")
    p.add_argument("--service", default="default")
    p.add_argument("--count", type=int, default=0, help="exit after this many estimates (default: run forever)")
    args = p.parse_args()
    seen, done = [0], threading.Event()

    def show(e: Estimate) -> None:
        x, y, z = e.pose[:3]
        print(f"{e.session} seq {e.seq}: ({x:+.3f}, {y:+.3f}, {z:+.3f}) m  {e.status}", flush=True)
        seen[0] += 1
        if args.count and seen[0] >= args.count:
            done.set()

    with TrackerClient(connect=[args.connect], service=args.service) as client:
        print("latest:", {s: int(e.seq) for s, e in client.poses().items()}, flush=True)  # one query, every session
        client.watch(show)
        print("watching", flush=True)
        done.wait()


if __name__ == "__main__":
    main()
