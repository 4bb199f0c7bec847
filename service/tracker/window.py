"""Each world's costs since its group's last update (eq. 1), and how far they tell the worlds apart
beyond their frame-to-frame noise. Torch ops inside the captured frame and update."""

from __future__ import annotations

import torch

from .evidence import noise_bound, separation
from .optimizers import HELD_COST

__all__ = ["CostWindow"]


class CostWindow:
    """The cost window of every group, state with a leading group axis, and each world's
    frame-to-frame scatter, which :meth:`separation` weighs the window's evidence by."""

    def __init__(self, groups: int, worlds: int, device: torch.device) -> None:
        self.sum = torch.zeros(groups, worlds, device=device)
        """Sum of each world's cost since its group's last update, (G, K)."""
        self.scatter = torch.zeros(groups, worlds, device=device)
        """Sum of each world's squared deviation from its group's mean cost of the frame, over the
        same frames, (G, K), over the worlds that hold the object."""
        self.evidence = torch.zeros(groups, worlds, device=device)
        """Each world's disagreement with the pose observations of the window, (G, K), in units of
        the spread of the group's contact costs (:mod:`.observations`)."""
        self.frames = torch.zeros(groups, 1, device=device)
        """Frames in each group's window, (G, 1). A group whose update was held back keeps its
        window over the next, so the counts differ between groups."""

    def add(self, cost: torch.Tensor) -> None:
        """One frame's cost (G, K); a world that lost its object scores from :data:`HELD_COST` up."""
        self.sum += cost
        held = cost < HELD_COST
        centre = torch.where(held, cost, 0.0).sum(-1, keepdim=True) / held.sum(-1, keepdim=True).clamp_min(1)
        self.scatter += torch.where(held, cost - centre, 0.0).square()
        self.frames += 1

    def means(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The window's mean cost per world, (G, K), and its highest and lowest among the worlds
        that still hold the object, (G, 1) each (-inf and inf where none does)."""
        mean = self.sum / self.frames.clamp_min(1)
        held = mean < HELD_COST
        top = torch.where(held, mean, -torch.inf).amax(-1, keepdim=True)
        bottom = torch.where(held, mean, torch.inf).amin(-1, keepdim=True)
        return mean, top, bottom

    def separation(self, floor: torch.Tensor | float = 0.0) -> torch.Tensor:
        """How far the window's costs separate each group's worlds beyond noise, (G,): the F ratio
        of :func:`.evidence.separation`, the scatter at least ``floor`` (G,) per frame."""
        frames = self.frames.clamp_min(1)
        return separation(self.means()[0], self.scatter / frames, frames[:, 0], floor)

    def noise_bound(self) -> torch.Tensor:
        """The separation noise alone stays below in about 95 % of windows of this many frames and
        held worlds, (G,) (:func:`.evidence.noise_bound`)."""
        held = (self.means()[0] < HELD_COST).sum(-1)
        return noise_bound(held.to(self.frames.dtype), self.frames[:, 0])

    def restart(self, keep: torch.Tensor | None = None, index: torch.Tensor | None = None) -> None:
        """Start the windows again after an update, but in the groups ``keep`` (G,) bool, whose update
        was held back: weak evidence that stays adds up there over windows until it separates the
        worlds. A world the update replaced there (it had lost its object) takes the window of its
        source ``index`` (G, K) with its state."""
        if keep is None or index is None:
            for t in (self.sum, self.scatter, self.evidence, self.frames):
                t.zero_()
            return
        keep = keep[:, None]
        for t in (self.sum, self.scatter, self.evidence):
            t.copy_(torch.where(keep, t.gather(1, index), 0.0))
        self.frames.masked_fill_(~keep, 0.0)

    def clear(self, groups: torch.Tensor) -> None:
        """Empty the windows of the re-seeded ``groups`` (G, 1) bool, frame counts too: a re-seeded
        group's mean costs are its new worlds' alone."""
        for t in (self.sum, self.scatter, self.evidence, self.frames):
            t.masked_fill_(groups, 0.0)
