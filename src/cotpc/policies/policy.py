"""The inference wrapper (``reset()`` + ``select_action(obs)`` over a batch of environments) and checkpoint I/O.

A checkpoint directory holds ``config.json`` (the full policy config, obs/action dims, dataset info, training
config) and ``model.safetensors`` (weights, normalisation statistics and k-means centres).
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import load_file, save_file

from cotpc.policies.config import PolicyConfig
from cotpc.policies.model import make_model

FORMAT = "cotpc-policy"


class CheckpointError(ValueError):
    """A run directory is missing, malformed, or its weights do not match its config."""


def config_to_dict(cfg: PolicyConfig) -> dict:
    return dataclasses.asdict(cfg)


def config_from_dict(d: dict) -> PolicyConfig:
    fields = {f.name for f in dataclasses.fields(PolicyConfig)}
    unknown = set(d) - fields
    if unknown:
        raise CheckpointError(f"unknown policy config keys {sorted(unknown)} (written by a newer cotpc?)")
    d = dict(d)
    d["cot_targets"] = tuple(d.get("cot_targets", ()))
    return PolicyConfig(**d)


def _atomic_write(path: Path, write) -> None:
    tmp = path.with_name(path.name + ".tmp")
    write(tmp)
    os.replace(tmp, path)


def save_checkpoint(directory: str | os.PathLike, model: torch.nn.Module, meta: dict) -> Path:
    """Write ``config.json`` + ``model.safetensors`` (each atomically: temporary file renamed into place)."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    info = {"format": FORMAT, "policy": config_to_dict(model.cfg), "obs_dim": model.obs_dim,
            "action_dim": model.action_dim, **meta}
    _atomic_write(directory / "model.safetensors", lambda p: save_file(state, str(p), metadata={"format": FORMAT}))
    _atomic_write(directory / "config.json", lambda p: p.write_text(json.dumps(info, indent=1, default=str)))
    return directory


def read_config(directory: str | os.PathLike) -> dict:
    directory = Path(directory)
    path = directory / "config.json"
    if not path.exists():
        raise CheckpointError(f"{directory}: no config.json; not a cotpc run directory")
    info = json.loads(path.read_text())
    if info.get("format") != FORMAT:
        raise CheckpointError(f"{path}: not a cotpc policy config (format {info.get('format')!r})")
    return info


def load_model(directory: str | os.PathLike, device: str = "cpu") -> tuple[torch.nn.Module, dict]:
    directory = Path(directory)
    info = read_config(directory)
    cfg = config_from_dict(info["policy"])
    model = make_model(cfg, info["obs_dim"], info["action_dim"], info.get("max_timestep", 1))
    weights = directory / "model.safetensors"
    if not weights.exists():
        raise CheckpointError(f"{directory}: no model.safetensors")
    load_state(model, load_file(str(weights)), f"{weights} (config: policy {cfg.name!r})")
    return model.to(device).eval(), info


def load_state(model: torch.nn.Module, state: dict, where: str) -> None:
    """``load_state_dict`` that names every mismatch (another policy, context, size or data dimensions)."""
    own = model.state_dict()
    missing = sorted(set(own) - set(state))
    unexpected = sorted(set(state) - set(own))
    shapes = [f"{k}: checkpoint {tuple(state[k].shape)} vs model {tuple(own[k].shape)}"
              for k in own if k in state and state[k].shape != own[k].shape]
    if missing or unexpected or shapes:
        lines = [f"{where}: the weights were trained with a different configuration or data dimensions"]
        if missing:
            lines.append(f"  missing: {', '.join(missing[:8])}{' ...' if len(missing) > 8 else ''}")
        if unexpected:
            lines.append(f"  unexpected: {', '.join(unexpected[:8])}{' ...' if len(unexpected) > 8 else ''}")
        lines += [f"  shape {s}" for s in shapes[:8]]
        raise CheckpointError("\n".join(lines))
    model.load_state_dict(state)


class Policy:
    """A trained policy acting in B environments at once; keeps each environment's last T states and actions.

    ``select_action(obs)`` takes (B, q) raw observations (one per environment) and returns (B, p) actions.
    ``reset()`` clears every environment's context; ``reset(envs)`` only those given as a boolean mask or
    indices (for vectorised environments that finish at different times).
    """

    def __init__(self, model: torch.nn.Module, info: dict | None = None, device: str = "cpu"):
        self.model = model.to(device).eval()
        self.info = info or {}
        self.device = torch.device(device)
        self.cfg: PolicyConfig = model.cfg
        self.obs_dim, self.action_dim = model.obs_dim, model.action_dim
        self.T = self.cfg.window
        n = model.norm
        self._obs_mean, self._obs_std, self._act_mean, self._act_std = n.obs_mean, n.obs_std, n.act_mean, n.act_std
        self._arange = torch.arange(self.T, device=self.device)
        self._states = None  # (B, T, q) normalised, oldest first
        self._actions = None  # (B, T, p) normalised; the last slot is filled after acting
        self._t = None  # (B,) timestep of the next observation
        self._n = None  # (B,) number of earlier steps held in the context

    @property
    def num_envs(self) -> int | None:
        return None if self._states is None else self._states.shape[0]

    @torch.inference_mode()
    def reset(self, envs=None) -> None:
        if envs is None or self._states is None:
            self._states = None
            return
        idx = torch.as_tensor(np.asarray(envs), device=self.device)
        if idx.dtype == torch.bool and idx.shape[0] != self._states.shape[0]:
            raise ValueError(f"reset mask has {idx.shape[0]} entries for {self._states.shape[0]} environments")
        self._t[idx] = 0
        self._n[idx] = 0

    def _allocate(self, B: int) -> None:
        dev = self.device
        self._states = torch.zeros(B, self.T, self.obs_dim, device=dev)
        self._actions = torch.zeros(B, self.T, self.action_dim, device=dev)
        self._t = torch.zeros(B, dtype=torch.long, device=dev)
        self._n = torch.zeros(B, dtype=torch.long, device=dev)

    @torch.inference_mode()
    def select_action(self, obs) -> np.ndarray:
        obs = torch.as_tensor(np.asarray(obs, dtype=np.float32), device=self.device)
        if obs.ndim == 1:
            raise ValueError(f"select_action takes a batch (B, {self.obs_dim}); got shape {tuple(obs.shape)}")
        if obs.ndim != 2 or obs.shape[1] != self.obs_dim:
            raise ValueError(
                f"observation has shape {tuple(obs.shape)}, but this policy was trained on {self.obs_dim}-dim "
                f"observations (data: {self.info.get('dataset', {}).get('path', '?')})"
            )
        B = obs.shape[0]
        if self._states is None:
            self._allocate(B)
        elif B != self._states.shape[0]:
            raise ValueError(f"got {B} observations for {self._states.shape[0]} environments; call reset() first")
        s = (obs - self._obs_mean) / self._obs_std
        if self.T > 1:  # shift the windows one step left (oldest out)
            self._states = torch.roll(self._states, -1, dims=1)
            self._actions = torch.roll(self._actions, -1, dims=1)
        self._states[:, -1] = s
        batch = {"states": self._states, "actions": self._actions,
                 "timesteps": self._t[:, None] - (self.T - 1) + self._arange}
        if self.T > 1 and bool((self._n < self.T - 1).any()):  # some context still starts inside the window
            batch["valid"] = self._arange[None, :] >= (self.T - 1 - self._n)[:, None]
        a = self.model.predict(batch)
        self._actions[:, -1] = a
        self._t += 1
        self._n += 1
        return (a * self._act_std + self._act_mean).cpu().numpy()


def load_policy(run_dir: str | os.PathLike, device: str = "cpu") -> Policy:
    """Load ``run_dir`` (``config.json`` + ``model.safetensors``) as a :class:`Policy`."""
    model, info = load_model(run_dir, device)
    return Policy(model, info, device)
