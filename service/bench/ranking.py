"""How well the cost ranks worlds by how wrong they are: per term, the Spearman rank correlation
between a world's cost and its object's true pose error (ADD), over each group's worlds, frame by
frame, while a tracker runs a suite.

A term that ranks well has a correlation near 1; one near 0 separates worlds by something other
than their pose (noise, or physics the pose does not show), and weighing it picks worlds at random.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from scipy.stats import rankdata

from inhand_tracker.protocol import Trajectory
from inhand_tracker.service.evaluation import add_error
from inhand_tracker.service.tracker import Frame, Tracker, TrackerConfig
from inhand_tracker.service.tracker.cost import TERM_NAMES
from inhand_tracker.service.tracker.sampling import sample_poses
from inhand_tracker.sim_backend import Population, PopulationConfig, catalog_object

from .recorder import Recording
from .suites import NOISE_LEVELS, robot_spec

__all__ = ["cost_ranking", "format_table", "rank_correlation"]


def rank_correlation(cost: np.ndarray, error: np.ndarray) -> np.ndarray:
    """Spearman's rho between ``cost`` (G, K, T) and ``error`` (G, K) over the K worlds of each
    group, per term, (G, T); NaN where either does not vary over the worlds (ties take their mean
    rank)."""
    rc = rankdata(cost, axis=1)
    re = rankdata(error, axis=1)[..., None]
    rc = rc - rc.mean(axis=1, keepdims=True)
    re = re - re.mean(axis=1, keepdims=True)
    norm = np.sqrt((rc**2).sum(axis=1) * (re**2).sum(axis=1))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(norm > 0, (rc * re).sum(axis=1) / norm, np.nan)


def cost_ranking(
    trajectories: Sequence[Trajectory],
    worlds: int = 40,
    method: str = "PBO",
    noise: str = "med",
    device: str = "auto",
    seed: int = 0,
    config: TrackerConfig | None = None,
) -> dict:
    """Track ``trajectories`` (one object) with ``method`` from a ``noise`` start, and correlate
    each cost term, the weighted frame cost and the window cost with the worlds' true error.

    Returns, per name, the mean rho over the (frame, group) pairs where it is defined and the
    fraction of pairs where it is (a term that never varies, such as slip before any slip, is
    undefined)."""
    obj = catalog_object(trajectories[0].object)
    rec = Recording.stack(trajectories)
    G = len(trajectories)
    pop = Population(robot_spec(trajectories[0].robot), obj, PopulationConfig(groups=G, worlds=worlds, device=device))
    tracker = Tracker(pop, config or TrackerConfig(seed=seed), methods=[method] * G)
    gen = torch.Generator().manual_seed(seed)
    sigma_t, sigma_r = NOISE_LEVELS[noise]
    start = sample_poses(torch.tensor(rec.initial_pose), sigma_t, sigma_r, 1, gen)[:, 0].numpy()
    start[:, 3:] /= np.linalg.norm(start[:, 3:], axis=-1, keepdims=True)
    tracker.start(start, rec.initial_q, sigma_t=np.full(G, sigma_t), sigma_r=np.full(G, sigma_r))
    points = obj.surface_points(500)
    weights = np.asarray(tracker.config.cost.weights or np.ones(len(TERM_NAMES)), np.float64)
    names = [*TERM_NAMES, "frame cost", "window cost"]
    rho: list[np.ndarray] = []
    for f in range(rec.frames):
        tracker.step(Frame(**{name: None if v is None else v[f] for name, v in rec.sensing.items()}))
        terms = tracker.cost.last_terms.double().cpu().numpy()  # (G, K, terms)
        # The window restarts at an update: right after one it holds nothing to rank.
        window = tracker.windows.means()[0].double().cpu().numpy()
        stacked = np.concatenate([terms, (terms * weights).sum(-1, keepdims=True), window[..., None]], axis=-1)
        error = add_error(points, rec.object_pose[f][:, None], pop.obs.object_pose.cpu().numpy())  # (G, K)
        live = f < rec.lengths
        rho.append(rank_correlation(stacked, error)[live])
    r = np.concatenate(rho)  # (frames x groups, terms)
    defined = np.isfinite(r)
    return {
        name: {
            "rho": float(np.nanmean(r[:, i])) if defined[:, i].any() else None,
            "defined": float(defined[:, i].mean()),
        }
        for i, name in enumerate(names)
    }


def format_table(results: dict[str, dict], title: str) -> str:
    """:func:`cost_ranking`'s results per object as a table: a row per cost term, each cell the
    correlation and the share of frames on which it was defined."""
    objects = list(results)
    lines = [f"Spearman rho of cost against true ADD over each group's worlds ({title})"]
    lines.append(f"{'term':<18}" + "".join(f"{o:>22}" for o in objects))
    for term in next(iter(results.values())):
        cells = []
        for o in objects:
            r = results[o][term]
            cells.append("-" if r["rho"] is None else f"{r['rho']:+.2f} ({100 * r['defined']:.0f} %)")
        lines.append(f"{term:<18}" + "".join(f"{c:>22}" for c in cells))
    return "\n".join(lines)
