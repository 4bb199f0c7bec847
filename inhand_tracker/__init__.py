"""inhand-tracker: the 6-DoF pose of an object held in a robot hand, from the robot's commands and
touch, tracked by a population of GPU physics simulations.

One import name for the whole project, so that nothing collides with other code in a workspace:
``inhand_tracker.client`` (the robot's side), ``inhand_tracker.protocol`` (the wire),
``inhand_tracker.service`` and ``inhand_tracker.sim_backend`` (the GPU side).
"""

from __future__ import annotations

from pathlib import Path

# An installed wheel holds the subpackages in this folder. A source checkout keeps them at the top
# of the tree (client/, protocol/, service/, sim_backend/), where the design has them; the tree's
# top joins this package's search path there, so a checkout runs as it is (the container, the
# GPU machine's copy, `python -m inhand_tracker.service.cli` from the root) without an install.
_tree = Path(__file__).resolve().parent.parent
if not (Path(__file__).parent / "service").is_dir() and (_tree / "service" / "cli").is_dir():
    __path__.append(str(_tree))
