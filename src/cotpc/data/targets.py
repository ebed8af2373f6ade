"""Chain-of-thought targets: for every timestep, the next and the last subskill state.

Indexing (our choice where the paper is ambiguous, see docs/subskills.md). A segment with inclusive end index
``c_i`` covers actions ``a(c_{i-1}+1) .. a(c_i)``. Its *key state* is ``obs[c_i + 1]``: the observation reached
after the segment's last action, i.e. the state in which that subskill is completed. This matches the official
CoTPC code (its key states are ``obs[step + 1]`` where ``step`` is the transition whose info flag turned true,
and the final key state is ``obs[-1]``). With ``k_i = c_i + 1`` the paper's rule reads unchanged:

- next subskill at time ``t``: ``obs[k_i]`` for the first ``k_i > t``. Since ``k_m = N > t`` for every
  ``t <= N - 1``, the "last one if none" case never arises.
- last subskill: ``obs[N]``, the final state of the demo (where the task is done).
"""

from __future__ import annotations

import numpy as np


def check_ends(ends, n: int) -> np.ndarray:
    """Validate segment end indices for a trajectory of ``n`` actions; return them as int64."""
    ends = np.asarray(ends)
    if ends.ndim != 1 or ends.size == 0:
        raise ValueError(f"segment ends must be a non-empty 1-D array, got shape {ends.shape}")
    if not np.issubdtype(ends.dtype, np.integer):
        if not np.all(np.isfinite(ends)) or np.any(ends != np.round(ends)):
            raise ValueError("segment ends must be integers")
    ends = ends.astype(np.int64)
    if ends[0] < 0 or np.any(np.diff(ends) <= 0):
        raise ValueError(f"segment ends must be >= 0 and strictly increasing, got {ends.tolist()}")
    if ends[-1] != n - 1:
        raise ValueError(f"the last segment end must be N-1 = {n - 1}, got {int(ends[-1])}")
    return ends


def key_state_indices(ends) -> np.ndarray:
    """Row of ``obs`` holding each subskill's key state: ``ends + 1`` (the state after the segment)."""
    return np.asarray(ends, dtype=np.int64) + 1


def cot_targets(obs: np.ndarray, ends: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-timestep CoT targets of one demo.

    Args:
        obs: (N+1, q) observations ``s(0..N)``.
        ends: (m,) inclusive segment end indices over the N actions (strictly increasing, last = N-1).

    Returns:
        ``(next_states, last_states)``, both (N, q) float32: row ``t`` holds ``obs[k]`` for the first key-state
        index ``k = c_i + 1 > t``, and ``obs[N]``.
    """
    obs = np.asarray(obs)
    if obs.ndim != 2 or obs.shape[0] < 2:
        raise ValueError(f"obs must be (N+1, q) with N >= 1, got shape {obs.shape}")
    n = obs.shape[0] - 1
    k = key_state_indices(check_ends(ends, n))
    t = np.arange(n)
    nxt = k[np.searchsorted(k, t, side="right")]  # first k > t; exists because k[-1] = N > t
    next_states = obs[nxt].astype(np.float32)
    last_states = np.repeat(obs[n : n + 1].astype(np.float32), n, axis=0)
    return next_states, last_states
