"""Playing recorded actions back through an evaluation (for tests and demo checks), any task with batched
environments."""

from __future__ import annotations

import numpy as np


class ReplayPolicy:
    """Plays back recorded action sequences (one per environment); zeros after the end."""

    def __init__(self, action_sequences: list[np.ndarray]):
        self.sequences = action_sequences
        self.action_dim = np.asarray(action_sequences[0]).shape[1]
        self.t = 0

    def reset(self) -> None:
        self.t = 0

    def select_action(self, obs: np.ndarray) -> np.ndarray:
        out = np.zeros((len(self.sequences), self.action_dim))
        for i, seq in enumerate(self.sequences):
            if self.t < len(seq):
                out[i] = seq[self.t]
        self.t += 1
        return out
