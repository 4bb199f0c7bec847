"""A robot replaying a trajectory file to a running tracking service, lock-step.

    inhand-tracker serve --listen tcp/127.0.0.1:7447 &
    python examples/robot_replay.py data/trajectories/smoke-foam_brick_pick_place_0.traj --frames 60
    python examples/robot_replay.py FILE --camera-hz 1    # with a (simulated) camera's pose estimates

Needs only the light client (`pip install inhand-tracker`): zenoh, msgpack, numpy, pydantic.
"""

from __future__ import annotations

import argparse

import numpy as np

from inhand_tracker.client import TrackerClient
from inhand_tracker.protocol import Trajectory


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("file")
    p.add_argument("--connect", default="tcp/127.0.0.1:7447")
    p.add_argument("--frames", type=int, default=0, help="frames to send (default all)")
    p.add_argument("--camera-hz", type=float, default=0.0, help="send the true pose with 5 mm of noise this often")
    args = p.parse_args()
    camera = np.random.default_rng(0)
    every = round(30 / args.camera_hz) if args.camera_hz > 0 else 0

    traj = Trajectory.load(args.file)
    frames = args.frames or traj.frames
    with TrackerClient(connect=[args.connect]) as client:
        start = traj.truth.initial_pose if traj.truth else None  # a real robot: its camera's estimate
        info = client.open_session(traj.robot, traj.object, start, q0=traj.truth.initial_q if traj.truth else None)
        print(f"session {info.session}", flush=True)
        for i in range(frames):
            frame = traj.frame(i, info.session)
            client.send(frame)  # controls, joints and whatever touch the file has
            if every and traj.truth is not None and i % every == 0:
                # A real robot's vision node sends its pose estimator's output with its covariance.
                seen = traj.truth.pose[i].copy()
                seen[:3] += camera.normal(0.0, 0.005, 3)
                client.observe_pose(seen, np.diag([0.005**2] * 3 + [0.05**2] * 3), stamp=frame.stamp)
            estimate = client.latest_pose(timeout=60, after_seq=i)
            if traj.truth is not None and (i % 10 == 0 or i == frames - 1):
                error = np.linalg.norm(traj.truth.pose[i, :3] - estimate.pose[:3]) * 1e3
                print(f"frame {i}: {estimate.status}, position error {error:.1f} mm", flush=True)
        status = client.status()
        print(
            f"done: {status.frames} frames, {status.observations} camera poses,"
            f" latency p50 {status.latency_p50_ms:.1f} ms",
            flush=True,
        )


if __name__ == "__main__":
    main()
