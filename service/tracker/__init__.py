"""The tracker: Algorithm 1 of the paper over every group of a population at once, as torch ops
on the population's device memory (cost, optimizers, sampling), captured as graphs."""

from .config import TrackerConfig
from .cost import TERM_NAMES, WEIGHTS, Cost, CostConfig, RealObservation
from .estimate import pose_modes
from .layout import ESTIMATE, Frame, GroupEstimates, InputLayout
from .optimizers import METHODS, OptimizerConfig
from .recovery import Recovery
from .settings import changed, registry, tracker_config
from .tracker import Tracker

__all__ = [
    "ESTIMATE",
    "METHODS",
    "TERM_NAMES",
    "WEIGHTS",
    "Cost",
    "CostConfig",
    "Frame",
    "GroupEstimates",
    "InputLayout",
    "OptimizerConfig",
    "RealObservation",
    "Recovery",
    "Tracker",
    "TrackerConfig",
    "changed",
    "pose_modes",
    "registry",
    "tracker_config",
]
