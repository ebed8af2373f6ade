"""Label a trajectory file with discovered subskills: ``traj_<i>/subskill_ends`` plus the parameters as attributes."""

from __future__ import annotations

import os
import time

import numpy as np

from cotpc.data.trajectories import TrajectorySet, load_trajectories, write_episode_datasets
from cotpc.subskills.discovery import discover_batch
from cotpc.subskills.evaluate import score

METHOD = "exact-dp"  # stored in the attributes: exact dynamic programming (not PELT)


def label_file(
    path: str | os.PathLike,
    beta: float,
    min_size: int = 1,
    cost: str = "mean-cosine",
    tol: int = 2,
    trajectories: TrajectorySet | None = None,
) -> tuple[dict, list[np.ndarray]]:
    """Discover subskills for every episode of ``path`` and store them, replacing earlier labels.

    Returns (summary, ends per episode). The summary holds the segmentation statistics, the seconds taken by
    discovery, and, when the episodes carry privileged ``key_steps``, precision / recall within ``tol`` steps.
    ``trajectories`` may pass the already loaded file to avoid reading it twice.
    """
    ts = load_trajectories(path) if trajectories is None else trajectories
    for ep in ts.episodes:
        if ep.num_steps < min_size:
            raise ValueError(f"{path}: traj_{ep.episode_id} has {ep.num_steps} actions, fewer than min_size={min_size}")
    t0 = time.perf_counter()
    ends = discover_batch([ep.actions for ep in ts.episodes], beta, min_size, cost)
    seconds = time.perf_counter() - t0
    attrs = {"beta": float(beta), "min_size": int(min_size), "method": METHOD, "cost": cost}
    write_episode_datasets(path, "subskill_ends", {ep.episode_id: e for ep, e in zip(ts.episodes, ends)}, attrs)
    has_keys = all("key_steps" in ep.extras for ep in ts.episodes)
    keys = [ep.extras["key_steps"] for ep in ts.episodes] if has_keys else None
    summary = {**attrs, "seconds": seconds, **score(ends, keys, tol)}
    return summary, ends


def ends_from_key_steps(key_steps: np.ndarray, num_actions: int) -> np.ndarray:
    """Segment ends whose key states are the privileged ``key_steps`` (state indices) plus the final state."""
    key_steps = np.asarray(key_steps, dtype=np.int64)
    if key_steps.ndim != 1 or np.any(key_steps < 1) or np.any(key_steps > num_actions):
        raise ValueError(f"key_steps {key_steps.tolist()} must be state indices in [1, {num_actions}]")
    return np.unique(np.concatenate([key_steps - 1, [num_actions - 1]]))


def label_file_from_key_steps(path: str | os.PathLike, trajectories: TrajectorySet | None = None):
    """Store the privileged ``key_steps`` of every episode as its subskills (the official code's setting, where
    key states come from the simulator; for comparison with discovered subskills). Returns (summary, ends)."""
    ts = load_trajectories(path) if trajectories is None else trajectories
    missing = [ep.episode_id for ep in ts.episodes if "key_steps" not in ep.extras]
    if missing:
        raise ValueError(f"{path}: traj_{missing[0]} (and {len(missing) - 1} more) have no key_steps to use")
    ends = [ends_from_key_steps(ep.extras["key_steps"], ep.num_steps) for ep in ts.episodes]
    attrs = {"beta": float("nan"), "min_size": 1, "method": "key-steps", "cost": "none"}
    write_episode_datasets(path, "subskill_ends", {ep.episode_id: e for ep, e in zip(ts.episodes, ends)}, attrs)
    summary = {**attrs, "seconds": 0.0, **score(ends, [ep.extras["key_steps"] for ep in ts.episodes], 0)}
    return summary, ends

