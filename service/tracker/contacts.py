"""Contact exploration: where a group's lowest window cost says the model's contacts are wrong,
its worlds draw their contact softness (time constant) and impratio around the model's and
perturb them at every update, as they do mass and friction. Torch ops on the population's
parameters, run inside the captured update."""

from __future__ import annotations

import logging

import numpy as np
import torch

from inhand_tracker.sim_backend import Population, PopulationConfig

from .config import ContactExploration
from .sampling import clipped_normal

__all__ = ["CONTACT_SPAN", "ContactExplorer", "say_overflow"]

log = logging.getLogger(__name__)

CONTACT_SPAN = float(np.log(4.0))
"""How far the worlds' contact parameters may stray from the model's, in their logarithm: a
factor of 4 either way spans soft rubber pads to rigid fingertips and MuJoCo's impratio from 2.5
to 40."""


class ContactExplorer:
    """The contact exploration of every group of a population."""

    def __init__(self, config: ContactExploration, pop: Population, gen: torch.Generator):
        self.config, self.pop, self.gen = config, pop, gen
        self.G, self.K, dev = pop.G, pop.K, pop.torch_device
        params = pop.params
        self.nominal = torch.tensor([params.nominal_timeconst, params.nominal_impratio], device=dev)
        """The model's contact time constant [s] and impratio, (2,)."""
        self._sigma0 = torch.tensor([config.softness_sigma0, config.impratio_sigma0], device=dev)
        self._sigma = torch.tensor([config.softness_sigma, config.impratio_sigma], device=dev)
        self.enabled = config.any and self.K >= max(2, config.contact_worlds)  # one world is the model
        """Whether any group of this population may explore its contacts."""
        self.open = torch.zeros(self.G, dtype=torch.bool, device=dev)
        """Whether each group's worlds explore their contacts, (G,) bool."""
        self._mismatched = torch.zeros(self.G, dtype=torch.int32, device=dev)
        """Updates in a row on which each group's lowest window cost was above the gate, (G,)."""

    def start(self, started: torch.Tensor, olp: torch.Tensor) -> None:
        """Groups ``started`` (G,) bool begin again: closed, unless there is no gate (not for OLP)."""
        ungated = self.enabled and self.config.contact_gate_cost <= 0
        self.open.masked_fill_(started, False).logical_or_(started & ~olp & ungated)
        self._mismatched.masked_fill_(started, 0)

    def current(self) -> torch.Tensor:
        """Each world's contact time constant [s] and impratio, (G, K, 2)."""
        return torch.stack([self.pop.params.timeconst, self.pop.params.impratio], -1)

    def around_model(self) -> torch.Tensor:
        """Logarithms of each world's contact time constant and impratio relative to the model's,
        drawn with their initial spreads and clipped to a factor of 4, (G, K, 2)."""
        zero = torch.zeros(self.G, self.K, 2, device=self.pop.torch_device)
        if not self.enabled or (self.config.softness_sigma0 <= 0 and self.config.impratio_sigma0 <= 0):
            return zero  # draws nothing: the generator's stream is what it was without them
        return clipped_normal(zero, self._sigma0, -CONTACT_SPAN, CONTACT_SPAN, self.gen)

    def seeded(self, sel: torch.Tensor, nominal: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The contacts of a seeding of groups ``sel`` (G, 1) bool: a group whose contacts were
        found wrong draws them again, the others keep the model's, as do the worlds ``nominal``
        (G, K) bool; groups not seeded keep theirs. Returns the time constants and impratios, (G, K) each."""
        drawn = self.around_model().masked_fill(~self.open[:, None, None] | nominal[..., None], 0.0).exp()
        return torch.where(sel[..., None], drawn * self.nominal, self.current()).unbind(-1)

    def gate(self, lowest: torch.Tensor, explores: torch.Tensor) -> torch.Tensor:
        """Count the updates in a row on which each group's ``lowest`` (G,) window cost among the
        worlds that hold the object stayed above the gate, and open the exploration of the groups
        ``explores`` (G,) bool where that count is reached. Returns the groups opened now, (G,)."""
        cfg = self.config
        mismatched = torch.isfinite(lowest) & (lowest > cfg.contact_gate_cost)
        self._mismatched.add_(1).mul_(mismatched)
        opens = (self._mismatched >= cfg.contact_gate_updates) & explores & ~self.open
        self.open.logical_or_(opens)
        return opens

    def explored(
        self, explore: torch.Tensor, scale: torch.Tensor, opens: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The resampled worlds' contacts after an update: perturbed where ``explore`` (G, K) and
        the group is open, by the per-update noise times ``scale`` (G, 1); drawn around the model
        in the groups ``opens`` (G,) opened now. Returns time constants and impratios, (G, K) each."""
        model = (self.current() / self.nominal).log()
        sigma = self._sigma * scale[..., None]
        step = clipped_normal(model, sigma, -CONTACT_SPAN, CONTACT_SPAN, self.gen)
        logs = torch.where((explore & self.open[:, None])[..., None], step, model)
        logs = torch.where(opens[:, None, None], self.around_model(), logs)
        return (logs.exp() * self.nominal).unbind(-1)


def say_overflow(groups: np.ndarray, config: PopulationConfig) -> None:
    """Say that worlds of ``groups`` ran out of contact room, and which settings give them more."""
    log.warning(
        "contacts: worlds of groups %s made more contacts than the %d a world holds (or more than its %d"
        " constraint rows); the excess was dropped from their physics: raise the population's"
        " contacts_per_world (and constraints_per_world)", groups.tolist(), config.contacts_per_world,
        config.constraints_per_world)  # fmt: skip
