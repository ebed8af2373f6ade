"""Unsupervised subskill discovery (paper Sec. 4.1) and the chain-of-thought targets built from it.

- :func:`discover` / :func:`discover_batch`: exact minimiser of the paper's segmentation objective.
- :func:`objective`: the objective J of a given segmentation.
- :func:`cot_targets`: per-timestep next / last subskill states for training.
"""

from cotpc.subskills.discovery import (
    COSTS,
    ZERO_ACTION_RTOL,
    ZERO_MEAN_RTOL,
    discover,
    discover_batch,
    objective,
)
from cotpc.data.targets import cot_targets, key_state_indices  # where training windows read them

PAPER_BETA = 0.05  # the paper's beta for single-arm tasks (0.02 for dual-arm); each task's own: cotpc.envs

__all__ = [
    "COSTS",
    "PAPER_BETA",
    "ZERO_ACTION_RTOL",
    "ZERO_MEAN_RTOL",
    "cot_targets",
    "discover",
    "discover_batch",
    "key_state_indices",
    "objective",
]
