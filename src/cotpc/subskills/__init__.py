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
from cotpc.subskills.targets import cot_targets, key_state_indices

PAPER_BETA = 0.05  # the paper's beta for single-arm tasks (0.02 for dual-arm)
# Moving Maze defaults, chosen from the key-step recovery table in docs/subskills.md (never from policy success).
MAZE_DEFAULT_COST = "sum-cosine"
MAZE_DEFAULT_BETA = 1.0

__all__ = [
    "COSTS",
    "MAZE_DEFAULT_BETA",
    "MAZE_DEFAULT_COST",
    "PAPER_BETA",
    "ZERO_ACTION_RTOL",
    "ZERO_MEAN_RTOL",
    "cot_targets",
    "discover",
    "discover_batch",
    "key_state_indices",
    "objective",
]
