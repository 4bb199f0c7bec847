"""Watch the estimates of every session of a tracking service (a dashboard, a logger).

python examples/pose_watcher.py --connect tcp/127.0.0.1:7447 --count 20
"""

from __future__ import annotations

import argparse
import threading

import zenoh

from protocol import Estimate, Keys, decode


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--connect", default="tcp/127.0.0.1:7447")
    p.add_argument("--service", default="default")
    p.add_argument("--count", type=int, default=0, help="exit after this many estimates (default: run forever)")
    args = p.parse_args()

    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("connect/endpoints", f'["{args.connect}"]')
    seen, done = [0], threading.Event()

    def show(sample: zenoh.Sample) -> None:
        e = decode(bytes(sample.payload.to_bytes()), Estimate)
        x, y, z = e.pose[:3]
        print(f"{e.session} seq {e.seq}: ({x:+.3f}, {y:+.3f}, {z:+.3f}) m  {e.status}", flush=True)
        seen[0] += 1
        if args.count and seen[0] >= args.count:
            done.set()

    with zenoh.open(conf) as session:
        session.declare_subscriber(Keys(args.service).every("pose"), show)
        print("watching", flush=True)
        done.wait()


if __name__ == "__main__":
    main()
