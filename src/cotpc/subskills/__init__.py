"""Unsupervised subskill discovery (paper Sec. 4.1) and the chain-of-thought targets built from it."""

from cotpc.subskills.targets import cot_targets, key_state_indices

__all__ = ["cot_targets", "key_state_indices"]
