"""Open-loop replay of recorded demos at other substep counts: how far the physics itself drifts.

Every world starts from a trajectory's true initial pose and joints with its hidden mass and
friction, and follows the recorded controls with no tracker. The object's position is compared
with the recorded truth and with the first substep count given (the reference). This is the
analysis behind "Substeps with the current tracker: what 6 and 4 cost" in docs/benchmarks.md:

    .venv/bin/python docs/accuracy/substeps-e/open_loop.py 32,16,8,6,4 bench-results/traj-e/paper-foam_brick_*.traj
    .venv/bin/python docs/accuracy/substeps-e/open_loop.py 4 --impratio 30 bench-results/traj-e/paper-foam_brick_*.traj

``--impratio`` sets the replays' friction impedance ratio (the truth keeps its 10). The files must
hold one object (one population); traj-e is the H100 truth of that section.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

import numpy as np
import torch

from protocol import Trajectory
from sim_backend.objects import catalog_object
from sim_backend.population import Population, PopulationConfig
from sim_backend.robots import HandSpec

WRIST_JOINTS = 6
"""The hand's first joints are its wrist's x, y, z, yaw, pitch, roll; the fingers follow."""


def replay(trajs: list[Trajectory], physics: PopulationConfig, frames: int) -> tuple[np.ndarray, np.ndarray]:
    """Object poses (G, F, 7) and measured joints (G, F, D) of one open-loop world per trajectory."""
    pop = Population(HandSpec(), catalog_object(trajs[0].object), physics)
    pop.reset_state(np.stack([t.truth.initial_pose for t in trajs]), np.stack([t.truth.initial_q for t in trajs]))
    pop.set_params(torch.tensor([[t.truth.mass] for t in trajs]), torch.tensor([[t.truth.friction] for t in trajs]))
    pose = np.empty((len(trajs), frames, 7))
    q = np.empty((len(trajs), frames, pop.D))
    for f in range(frames):
        pop.set_targets(np.stack([t.controls[f] for t in trajs]))
        pop.step()
        pose[:, f] = pop.obs.object_pose[:, 0].cpu().numpy()
        q[:, f] = pop.obs.q[:, 0].cpu().numpy()
    return pose, q


def main(counts: list[int], files: list[str], impratio: float | None = None) -> None:
    trajs = [Trajectory.load(f) for f in files]
    frames = min(t.frames for t in trajs)
    truth = np.stack([t.truth.pose[:frames] for t in trajs])
    measured_q = np.stack([t.q[:frames] for t in trajs])
    marks = [150, 300, 600, 900, frames - 1]
    print("tracks:", ", ".join(t.name for t in trajs))
    reference = None
    for n in counts:
        t0 = time.perf_counter()
        physics = PopulationConfig(groups=len(trajs), worlds=1, substeps=n)
        if impratio is not None:
            physics = replace(physics, impratio=impratio)
        pose, q = replay(trajs, physics, frames)
        seconds = time.perf_counter() - t0
        to_truth = np.linalg.norm(pose[..., :3] - truth[..., :3], axis=-1) * 1e3
        line = (
            f"{n:2d} substeps ({seconds:4.0f} s): to the truth, mean per track {to_truth.mean(1).round(1)} mm, "
            f"at frames {marks} {to_truth[:, marks].mean(0).round(1)} mm"
        )
        if reference is None:
            reference = pose
        else:
            to_ref = np.linalg.norm(pose[..., :3] - reference[..., :3], axis=-1) * 1e3
            line += f"; to {counts[0]} substeps {to_ref.mean(1).round(1)} mm"
        finger = np.abs(q - measured_q)[..., WRIST_JOINTS:].mean(axis=(0, 1)) * 1e3
        print(line + f"; finger joints off the recorded ones by {finger.mean():.2f} mrad (max {finger.max():.2f})")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("substeps", help="comma-separated substep counts, the first the reference: 32,8,4")
    parser.add_argument("files", nargs="+", help="trajectory files (.traj) of one object")
    parser.add_argument("--impratio", type=float, default=None, help="the replays' impratio (default the population's)")
    args = parser.parse_args()
    main([int(n) for n in args.substeps.split(",")], args.files, args.impratio)
