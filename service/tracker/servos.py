"""Servo exploration: where the model check says a finger of a group's hand does not follow the
robot's joints, the group's worlds draw a strength for that finger's servos around the config's
and perturb it at every update, as they do mass and friction; resampling keeps the strengths
whose joints follow the robot's. Torch ops on the model's per-DOF arrays, run inside the
captured update."""

from __future__ import annotations

import numpy as np
import torch

from inhand_tracker.sim_backend import Population
from inhand_tracker.sim_backend.kinematics import joint_chains

from .config import ServoExploration
from .sampling import clipped_normal

__all__ = ["SCALED_SERVOS", "SERVO_SPAN", "ServoExplorer"]

SERVO_SPAN = float(np.log(4.0))
"""How far a chain's strength may stray from the config's, in its logarithm."""

SCALED_SERVOS = ("ke", "kd", "effort", "damping")
"""What a strength scales together: at its effort limit a finger moves at effort over damping, so
a servo that is weaker in gain alone is not what a weaker motor is."""


class ServoExplorer:
    """The servo exploration of every group of a population, per chain (finger, wrist) of its robot."""

    def __init__(self, config: ServoExploration, pop: Population, seed: int):
        self.config, self.pop = config, pop
        G, K, dev = pop.G, pop.K, pop.torch_device
        self.gen = torch.Generator(device=dev)
        """Its own random stream: the tracker's draws the same numbers with it on or off."""
        self.gen.manual_seed(seed + 1)
        self.enabled = config.servo_sigma0 > 0 and K >= config.servo_worlds
        """Whether any group of this population may explore its servos."""
        chains = joint_chains(pop.model, pop.layout)
        self.names = tuple(pop.layout.joint_names[i] for i in np.unique(chains, return_index=True)[1])
        """Each chain by its first joint's name, (C,)."""
        self._chain = torch.as_tensor(chains, device=dev)
        C = len(self.names)
        with pop.on_stream():
            self.nominal = {name: pop.servos(name) for name in SCALED_SERVOS} if self.enabled else {}
        """The config's settings, (G, K, D) each."""
        self.log_strength = torch.zeros(G, K, C, device=dev)
        """Each world's strength per chain, the logarithm of its factor on the config's, (G, K, C)."""
        self.open = torch.zeros(G, C, dtype=torch.bool, device=dev)
        """Whether each group's worlds explore each chain, (G, C) bool."""
        self._mismatched = torch.zeros(G, C, dtype=torch.int32, device=dev)
        """Updates in a row on which a joint of the chain was past the gate, (G, C)."""

    def start(self, started: torch.Tensor) -> None:
        """Groups ``started`` (G,) bool begin again with the config's servos, closed."""
        if not self.enabled:
            return
        self.open.masked_fill_(started[:, None], False)
        self._mismatched.masked_fill_(started[:, None], 0)
        self.log_strength.masked_fill_(started[:, None, None], 0.0)
        self._write()

    def gate(self, rms: torch.Tensor, explores: torch.Tensor) -> torch.Tensor:
        """Count the updates in a row on which a joint of each chain ran further than the gate
        from the robot's (``rms`` (G, D), the model check's), and open the chains of groups
        ``explores`` (G,) bool where that count is reached. Returns the chains opened now, (G, C)."""
        worst = torch.zeros_like(self.open, dtype=rms.dtype)
        worst.scatter_reduce_(1, self._chain.expand_as(rms), rms, "amax")
        self._mismatched.add_(1).mul_(worst > self.config.servo_gate)
        opens = (self._mismatched >= self.config.servo_gate_updates) & explores[:, None] & ~self.open
        self.open.logical_or_(opens)
        return opens

    def explored(self, index: torch.Tensor, explore: torch.Tensor, scale: torch.Tensor, opens: torch.Tensor) -> None:
        """After an update: each world takes the strengths of the world ``index`` (G, K) whose
        parameters it took, perturbed where ``explore`` (G, K) and the chain is open, by the
        per-update noise times ``scale`` (G, 1); chains ``opens`` (G, C) opened now draw theirs
        around the config's (one world keeps the config's); then the model takes them."""
        cfg = self.config
        logs = self.log_strength.gather(1, index[..., None].expand_as(self.log_strength))
        step = clipped_normal(logs, cfg.servo_sigma * scale[..., None], -SERVO_SPAN, SERVO_SPAN, self.gen)
        logs = torch.where(explore[..., None] & self.open[:, None], step, logs)
        drawn = clipped_normal(torch.zeros_like(logs), cfg.servo_sigma0, -SERVO_SPAN, SERVO_SPAN, self.gen)
        drawn[:, 0] = 0.0
        self.log_strength.copy_(torch.where(opens[:, None], drawn, logs))
        self._write()

    def strengths(self, weights: torch.Tensor) -> dict[str, torch.Tensor]:
        """Each group's strength factor per chain under ``weights`` (G, K) (the estimate's, summing
        to 1): a weighted geometric mean, by chain name, (G,) each."""
        mean = (weights[..., None] * self.log_strength).sum(1).exp()
        return {name: mean[:, c] for c, name in enumerate(self.names)}

    def _write(self) -> None:
        factor = self.log_strength.exp()[..., self._chain]  # (G, K, D)
        self.pop.write_servos({name: value * factor for name, value in self.nominal.items()})
