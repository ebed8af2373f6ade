"""Unsupervised subskill discovery (paper Sec. 4.1) and the chain-of-thought targets built from it.

- :func:`discover` / :func:`discover_batch`: exact minimiser of the paper's segmentation objective.
- :func:`objective`: the objective J of a given segmentation.
- :func:`cot_targets`: per-timestep next / last subskill states for training.
"""

from cotpc.subskills.discovery import ZERO_ACTION_RTOL, ZERO_MEAN_RTOL, discover, discover_batch, objective
from cotpc.subskills.targets import cot_targets, key_state_indices

__all__ = [
    "ZERO_ACTION_RTOL",
    "ZERO_MEAN_RTOL",
    "cot_targets",
    "discover",
    "discover_batch",
    "key_state_indices",
    "objective",
]
