"""Reading and writing demonstrations in ManiSkill3's trajectory format.

A dataset ``NAME`` is two files:

- ``NAME.h5``: one group ``traj_<i>`` per episode with ``obs`` (N+1, q), ``actions`` (N, p), ``success`` (N,),
  and optional extras (``env_states``, ``key_steps``, ``subskill_ends``, ...).
- ``NAME.json``: ``env_info`` (``env_id``, ``env_kwargs``, ``max_episode_steps``) and ``episodes``, a list of
  ``episode_id``, ``reset_kwargs`` (with the ``seed``), ``control_mode`` and ``elapsed_steps``.

Everything that reads a file goes through :func:`load_trajectories`, which checks the file thoroughly and raises
:class:`TrajectoryFormatError` with the file and episode named, so bad input never surfaces as a traceback from
deep inside training.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np


class TrajectoryFormatError(ValueError):
    """A trajectory file is malformed, inconsistent with its JSON, or holds invalid numbers."""


@dataclass
class Episode:
    """One demonstration: ``obs`` has one more row than ``actions`` (the state after the last action)."""

    obs: np.ndarray
    actions: np.ndarray
    success: np.ndarray
    episode_id: int
    reset_kwargs: dict[str, Any] = field(default_factory=dict)
    control_mode: str | None = None
    extras: dict[str, np.ndarray] = field(default_factory=dict)
    extra_attrs: dict[str, dict[str, Any]] = field(default_factory=dict)  # HDF5 attributes of each extra

    @property
    def num_steps(self) -> int:
        return int(self.actions.shape[0])


@dataclass
class TrajectorySet:
    episodes: list[Episode]
    env_info: dict[str, Any]
    meta: dict[str, Any] = field(default_factory=dict)  # other top-level JSON keys (source_type, ...)

    @property
    def obs_dim(self) -> int:
        return int(self.episodes[0].obs.shape[1])

    @property
    def action_dim(self) -> int:
        return int(self.episodes[0].actions.shape[1])

    def __len__(self) -> int:
        return len(self.episodes)


def split_paths(path: str | os.PathLike) -> tuple[Path, Path]:
    """``DIR/NAME``, ``DIR/NAME.h5`` or ``DIR/NAME.json`` -> (``DIR/NAME.h5``, ``DIR/NAME.json``)."""
    path = Path(path)
    stem = path.with_suffix("") if path.suffix in (".h5", ".json") else path
    return stem.with_suffix(".h5"), stem.with_suffix(".json")


def save_trajectories(path: str | os.PathLike, trajectories: TrajectorySet) -> tuple[Path, Path]:
    """Write ``NAME.h5`` + ``NAME.json`` atomically (temporary files renamed into place)."""
    h5_path, json_path = split_paths(path)
    h5_path.parent.mkdir(parents=True, exist_ok=True)
    for ep in trajectories.episodes:
        _check_episode(ep, str(h5_path))
    tmp_h5, tmp_json = h5_path.with_suffix(".h5.tmp"), json_path.with_suffix(".json.tmp")
    with h5py.File(tmp_h5, "w") as f:
        for ep in trajectories.episodes:
            g = f.create_group(f"traj_{ep.episode_id}")
            g.create_dataset("obs", data=np.asarray(ep.obs, dtype=np.float32))
            g.create_dataset("actions", data=np.asarray(ep.actions, dtype=np.float32))
            g.create_dataset("success", data=np.asarray(ep.success, dtype=bool))
            for name, value in ep.extras.items():
                d = g.create_dataset(name, data=value)
                d.attrs.update(ep.extra_attrs.get(name, {}))
    episodes_json = [
        {
            "episode_id": ep.episode_id,
            "reset_kwargs": ep.reset_kwargs,
            "control_mode": ep.control_mode,
            "elapsed_steps": ep.num_steps,
            "success": bool(ep.success[-1]) if ep.num_steps else False,
        }
        for ep in trajectories.episodes
    ]
    with open(tmp_json, "w") as f:
        json.dump({**trajectories.meta, "env_info": trajectories.env_info, "episodes": episodes_json}, f, indent=1)
    os.replace(tmp_h5, h5_path)
    os.replace(tmp_json, json_path)
    return h5_path, json_path


def load_trajectories(path: str | os.PathLike, extras: tuple[str, ...] | None = None) -> TrajectorySet:
    """Load and validate a trajectory file pair.

    ``extras`` names the optional per-episode datasets to load (default: all that are present besides
    ``obs``/``actions``/``success``).
    """
    if Path(path).is_dir():
        found = sorted(p.name for p in Path(path).glob("*.h5"))
        raise TrajectoryFormatError(f"{path} is a directory; pass one trajectory file in it"
                                    + (f" ({', '.join(found)})" if found else " (it holds no .h5 file)"))
    h5_path, json_path = split_paths(path)
    if not h5_path.exists():
        raise TrajectoryFormatError(f"{h5_path}: no such trajectory file")
    if not json_path.exists():
        raise TrajectoryFormatError(f"{json_path}: missing; ManiSkill3 trajectories come as NAME.h5 + NAME.json")
    try:
        with open(json_path) as f:
            info = json.load(f)
    except json.JSONDecodeError as e:
        raise TrajectoryFormatError(f"{json_path}: not valid JSON ({e})") from None
    if not isinstance(info, dict) or "episodes" not in info or "env_info" not in info:
        raise TrajectoryFormatError(f"{json_path}: needs top-level keys 'env_info' and 'episodes'")

    episodes = []
    try:
        f = h5py.File(h5_path, "r")
    except OSError as e:
        raise TrajectoryFormatError(f"{h5_path}: not a readable HDF5 file ({e})") from None
    with f:
        for record in info["episodes"]:
            eid = record.get("episode_id")
            key = f"traj_{eid}"
            if key not in f:
                raise TrajectoryFormatError(f"{h5_path}: episode {eid} is listed in {json_path.name} but has no group {key}")
            g = f[key]
            for name in ("obs", "actions"):
                if name not in g:
                    raise TrajectoryFormatError(f"{h5_path}:{key}: missing dataset '{name}'")
            if not isinstance(g["obs"], h5py.Dataset):
                raise TrajectoryFormatError(
                    f"{h5_path}:{key}: 'obs' is a group (dict observations); convert to a flat state vector first"
                )
            obs = np.asarray(g["obs"][()], dtype=np.float32)
            actions = np.asarray(g["actions"][()], dtype=np.float32)
            success = np.asarray(g["success"][()], dtype=bool) if "success" in g else np.zeros(len(actions), bool)
            names = [n for n in g.keys() if n not in ("obs", "actions", "success")] if extras is None else extras
            present = [n for n in names if n in g and isinstance(g[n], h5py.Dataset)]
            ep_extras = {n: np.asarray(g[n][()]) for n in present}
            ep_attrs = {n: dict(g[n].attrs) for n in present}
            ep = Episode(
                obs=obs,
                actions=actions,
                success=success,
                episode_id=int(eid),
                reset_kwargs=record.get("reset_kwargs", {}),
                control_mode=record.get("control_mode"),
                extras=ep_extras,
                extra_attrs=ep_attrs,
            )
            _check_episode(ep, f"{h5_path}:{key}")
            episodes.append(ep)
    if not episodes:
        raise TrajectoryFormatError(f"{h5_path}: holds no episodes")
    q, p = episodes[0].obs.shape[1], episodes[0].actions.shape[1]
    for ep in episodes:
        if ep.obs.shape[1] != q or ep.actions.shape[1] != p:
            raise TrajectoryFormatError(
                f"{h5_path}:traj_{ep.episode_id}: obs/action dims {ep.obs.shape[1]}/{ep.actions.shape[1]} differ from "
                f"the first episode's {q}/{p}"
            )
    meta = {k: v for k, v in info.items() if k not in ("env_info", "episodes")}
    return TrajectorySet(episodes=episodes, env_info=info["env_info"], meta=meta)


def _check_episode(ep: Episode, where: str) -> None:
    if ep.obs.ndim != 2 or ep.actions.ndim != 2:
        raise TrajectoryFormatError(
            f"{where}: obs must be (N+1, q) and actions (N, p); got {ep.obs.shape} and {ep.actions.shape}"
        )
    if ep.actions.shape[0] == 0:
        raise TrajectoryFormatError(f"{where}: episode has no actions")
    if ep.obs.shape[0] != ep.actions.shape[0] + 1:
        raise TrajectoryFormatError(
            f"{where}: obs has {ep.obs.shape[0]} rows but actions {ep.actions.shape[0]}; expected N+1 and N"
        )
    if len(ep.success) != ep.actions.shape[0]:
        raise TrajectoryFormatError(f"{where}: success has {len(ep.success)} entries, expected {ep.actions.shape[0]}")
    for name, arr in (("obs", ep.obs), ("actions", ep.actions)):
        if not np.all(np.isfinite(arr)):
            bad = np.argwhere(~np.isfinite(arr))[0]
            raise TrajectoryFormatError(f"{where}: {name} holds NaN/inf (first at index {tuple(int(i) for i in bad)})")
    if not ep.actions.any():  # a single zero action is a legitimate pause; a whole episode of them is no demo
        raise TrajectoryFormatError(f"{where}: every action of this episode is zero ({ep.actions.shape[0]} steps): "
                                    f"a failed recording or the wrong dataset; remove the episode")


def write_episode_datasets(
    path: str | os.PathLike, name: str, values: dict[int, np.ndarray], attrs: dict[str, Any] | None = None
) -> None:
    """Store (or replace) dataset ``traj_<i>/<name>`` for each episode id in ``values``, with ``attrs``."""
    h5_path, _ = split_paths(path)
    with h5py.File(h5_path, "r+") as f:
        for eid, value in values.items():
            g = f[f"traj_{eid}"]
            if name in g:
                del g[name]
            d = g.create_dataset(name, data=value)
            d.attrs.update(attrs or {})
