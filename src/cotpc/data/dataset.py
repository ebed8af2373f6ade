"""Demonstrations as flat tensors, with vectorised sampling of context windows.

All timesteps of all episodes are concatenated once into ``(S, q)`` / ``(S, p)`` tensors; a batch of windows is
a single gather with an index matrix ``end[:, None] - (T-1) + arange(T)`` — no per-sample Python. A window
that would start before its episode is left-padded (``valid`` False; the padded entries hold the episode's
first step, and the model masks them out).
With ``future_actions`` F > 0 a window also carries the F actions after its last one (Diffusion Policy's action
chunks); past the episode's end they repeat its last action. With ``future_states`` F > 0 it carries the F states
after its last one, s(t+1) .. s(t+F) (Decision Diffuser's plans), the episode's final observation s(N) included;
past it they repeat s(N).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from cotpc.data.targets import check_ends, cot_targets, key_state_indices
from cotpc.data.trajectories import Episode, TrajectorySet


class MissingSubskillsError(ValueError):
    """The data file has no ``subskill_ends`` but the policy needs CoT targets."""


@dataclass
class Stats:
    obs_mean: torch.Tensor
    obs_std: torch.Tensor
    act_mean: torch.Tensor
    act_std: torch.Tensor

    @staticmethod
    def of(obs: np.ndarray, actions: np.ndarray, obs_std_floor: float = 0.0) -> "Stats":
        """Mean and std of each dimension. ``obs_std_floor`` raises an observation std below it to it (in the
        observation's units): a near-constant dimension is otherwise blown up by 1 / std, so a move the demos
        never made reads as thousands of stds (Stack Cube: cube B's height, std 1e-5 m)."""
        def mean_std(x, floor=0.0):
            x = torch.as_tensor(x, dtype=torch.float64)
            std = x.std(0, unbiased=False)
            std = torch.where(std < 1e-6, torch.ones_like(std), std)  # a constant dimension stays as is
            return x.mean(0).float(), std.clamp_min(floor).float()

        return Stats(*mean_std(obs, obs_std_floor), *mean_std(actions))

    def small_obs_std(self, below: float) -> list[int]:
        """Observation dimensions whose (finite) std is below ``below``."""
        std = self.obs_std
        return [int(d) for d in torch.nonzero(torch.isfinite(std) & (std < below)).flatten()]

    def ignoring(self, obs_dims) -> "Stats":
        """These statistics with the observation dimensions ``obs_dims`` normalised to 0 whatever their value (mean
        0, std infinity): every path that normalises with them (training windows, CoT targets, validation, the
        saved policy at inference) then hides those dimensions from the model."""
        if not len(obs_dims):
            return self
        mean, std = self.obs_mean.clone(), self.obs_std.clone()
        mean[list(obs_dims)], std[list(obs_dims)] = 0.0, float("inf")
        return Stats(mean, std, self.act_mean, self.act_std)


def split_episodes(n: int, val_fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Seeded split of episode indices into (train, val); val gets round(n * fraction) (>= 1 if fraction > 0
    and n >= 2)."""
    n_val = int(round(n * val_fraction))
    if val_fraction > 0 and n >= 2:
        n_val = max(n_val, 1)
    n_val = min(n_val, n - 1)
    perm = np.random.default_rng(seed).permutation(n)
    return np.sort(perm[n_val:]), np.sort(perm[:n_val])


def episode_cot_targets(ep, targets: tuple[str, ...], rng: np.random.Generator, where: str) -> np.ndarray:
    """(N, k*q) CoT targets of one episode, in the order of ``targets``."""
    parts = []
    if "next" in targets or "last" in targets:
        if "subskill_ends" not in ep.extras:
            raise MissingSubskillsError(
                f"{where}: episode {ep.episode_id} has no subskill_ends, which this policy needs as CoT targets; "
                f"run `cotpc segment DATA.h5 --beta 0.05` (0.02 for dual-arm tasks) on the data file first"
            )
        nxt, last = cot_targets(ep.obs, ep.extras["subskill_ends"])
    n = ep.num_steps
    for name in targets:
        if name == "next":
            parts.append(nxt)
        elif name == "last":
            parts.append(last)
        elif name == "random":
            # a random *future* observation s(r), r uniform in {t+1..N}, drawn once per timestep (seeded)
            t = np.arange(n)
            r = t + 1 + np.floor(rng.random(n) * (n - t)).astype(np.int64)
            parts.append(ep.obs[r])
        else:
            raise ValueError(f"unknown CoT target {name!r}")
    return np.concatenate(parts, axis=1).astype(np.float32)


def boundary_weights(ep, weight: float, radius: int, where: str) -> np.ndarray:
    """(N,) sampling weight of each window end t of one episode: ``weight`` where t is within ``radius`` steps
    of a boundary between two of its subskills (a key-state index c_i + 1 other than the episode's end), 1
    elsewhere. Where a policy's mistakes tend to be fatal, between one subskill and the next (in the Moving Maze,
    getting onto and across a bridge), these steps are a small share of a demo; the weight trains on them more
    often without changing any target."""
    if not (weight > 0 and math.isfinite(weight)) or radius < 0:
        raise ValueError(f"boundary weight must be a finite number > 0 and radius >= 0, got {weight}, {radius}")
    if "subskill_ends" not in ep.extras:
        raise MissingSubskillsError(
            f"{where}: episode {ep.episode_id} has no subskill_ends, which --boundary-weight needs; "
            f"run `cotpc segment DATA.h5` on the data file first"
        )
    n = ep.num_steps
    keys = key_state_indices(check_ends(ep.extras["subskill_ends"], n))[:-1]  # the last one is the episode's end
    t = np.arange(n)
    near = (np.abs(t[:, None] - keys[None, :]) <= radius).any(1)  # all False for a one-subskill episode
    return np.where(near, weight, 1.0)


class WindowDataset:
    """Context windows of a subset of episodes, normalised, as tensors on one device."""

    def __init__(
        self,
        trajs: TrajectorySet,
        episodes: np.ndarray | list[int],
        context: int,
        stats: Stats,
        cot_targets: tuple[str, ...] = (),
        seed: int = 0,
        device: str | torch.device = "cpu",
        where: str = "data",
        future_actions: int = 0,
        future_states: int = 0,
        boundary_weight: float = 1.0,
        boundary_radius: int = 2,
    ):
        eps = [trajs.episodes[i] for i in episodes]
        if not eps:
            raise ValueError("no episodes")
        self.context, self.device = context, torch.device(device)
        lengths = np.array([ep.num_steps for ep in eps])
        starts = np.concatenate([[0], np.cumsum(lengths)[:-1]])
        obs = np.concatenate([ep.obs[:-1] for ep in eps])  # s(0..N-1): the states that get an action
        act = np.concatenate([ep.actions for ep in eps])
        dev = self.device
        self.obs = ((torch.as_tensor(obs) - stats.obs_mean) / stats.obs_std).to(dev)
        self.actions = ((torch.as_tensor(act) - stats.act_mean) / stats.act_std).to(dev)
        self.timesteps = torch.as_tensor(np.concatenate([np.arange(n) for n in lengths])).to(dev)
        self.ep_start = torch.as_tensor(np.repeat(starts, lengths)).to(dev)
        self.ep_last = torch.as_tensor(np.repeat(starts + lengths - 1, lengths)).to(dev)
        self.future = torch.arange(1, future_actions + 1, device=dev)  # offsets of the future actions
        self.future_s = torch.arange(1, future_states + 1, device=dev)  # offsets of the future states
        if future_states:
            # every observation s(0..N) of each episode, normalised: self.obs lacks the final s(N), which has no
            # action but is the target of the last transition; row of s(t) = flat index of t + episode number
            all_obs = np.concatenate([ep.obs for ep in eps])
            self.all_obs = ((torch.as_tensor(all_obs) - stats.obs_mean) / stats.obs_std).to(dev)
            self.ep_number = torch.as_tensor(np.repeat(np.arange(len(eps)), lengths)).to(dev)
        self.cot = None
        if cot_targets:
            rng = np.random.default_rng(seed)
            cot = np.concatenate([episode_cot_targets(ep, cot_targets, rng, where) for ep in eps])
            k = len(cot_targets)
            cot = (torch.as_tensor(cot).view(-1, k, obs.shape[1]) - stats.obs_mean) / stats.obs_std
            self.cot = cot.view(-1, k * obs.shape[1]).to(dev)
        self.size = int(lengths.sum())
        self.offsets = torch.arange(context, device=dev) - (context - 1)
        self.cum_weight = None  # uniform window ends unless boundary_weight != 1
        if boundary_weight != 1.0:
            w = np.concatenate([boundary_weights(ep, boundary_weight, boundary_radius, where) for ep in eps])
            self.cum_weight = torch.as_tensor(np.cumsum(w)).to(dev)

    def __len__(self) -> int:
        return self.size

    def windows(self, ends: torch.Tensor) -> dict[str, torch.Tensor]:
        """Windows ending at flat indices ``ends`` (B,)."""
        idx = ends[:, None] + self.offsets  # (B, T)
        start = self.ep_start[ends][:, None]
        valid = idx >= start
        idx = torch.maximum(idx, start)  # padding repeats the first step; it is masked out anyway
        batch = {
            "states": self.obs[idx],
            "actions": self.actions[idx],
            "timesteps": self.timesteps[idx],
            "valid": valid,
        }
        if self.cot is not None:
            batch["cot"] = self.cot[idx]
        if len(self.future):  # a(t+1) .. a(t+F), the episode's last action repeated past its end
            future = torch.minimum(ends[:, None] + self.future, self.ep_last[ends][:, None])
            batch["future_actions"] = self.actions[future]
        if len(self.future_s):  # s(t+1) .. s(t+F), the episode's final state s(N) repeated past its end
            row = ends + self.ep_number[ends]  # row of s(t) in all_obs
            final = self.ep_last[ends] + self.ep_number[ends] + 1  # row of s(N)
            batch["future_states"] = self.all_obs[torch.minimum(row[:, None] + self.future_s, final[:, None])]
        return batch

    def sample_ends(self, batch_size: int, generator: torch.Generator) -> torch.Tensor:
        """(B,) flat indices of random window ends: uniform, or in proportion to the boundary weights."""
        dev = generator.device
        if self.cum_weight is None:
            return torch.randint(self.size, (batch_size,), generator=generator, device=dev).to(self.device)
        # inverse-CDF draw from the per-step weights: one searchsorted, no Python per sample
        u = torch.rand(batch_size, generator=generator, device=dev, dtype=torch.float64).to(self.device)
        return torch.searchsorted(self.cum_weight, u * self.cum_weight[-1], right=True).clamp_(max=self.size - 1)

    def sample(self, batch_size: int, generator: torch.Generator, state_noise: float = 0.0) -> dict[str, torch.Tensor]:
        """Random window ends (uniform, or weighted towards subskill boundaries with ``boundary_weight``), plus
        the random CoT-mask length l in {0..T-1} per sample.

        ``state_noise`` > 0 adds Gaussian noise of that standard deviation (normalised units) to the input states
        of the window, never to a target (actions, CoT targets, future states): the history then no longer
        identifies a training demo exactly, which is how context policies memorise few configurations."""
        dev = generator.device  # a generator on the data's device samples there (no host round trip on a GPU)
        batch = self.windows(self.sample_ends(batch_size, generator))
        batch["cot_hide"] = torch.randint(self.context, (batch_size,), generator=generator, device=dev).to(self.device)
        if state_noise > 0:
            noise = torch.randn(batch["states"].shape, generator=generator, device=dev).to(self.device)
            batch["states"] = batch["states"] + state_noise * noise
        return batch


def synthetic_trajectories(
    n_episodes: int = 16, obs_dim: int = 6, action_dim: int = 2, length: int = 30, n_segments: int = 3,
    seed: int = 0, env_id: str = "Synthetic-v0",
) -> TrajectorySet:
    """Small learnable demos for tests and benchmarks (with ``subskill_ends``): each episode moves a point in
    ``n_segments`` straight segments of random direction; the observation is the position followed by the
    episode's segment directions (so the right action is predictable from the state and the history)."""
    rng = np.random.default_rng(seed)
    episodes = []
    for i in range(n_episodes):
        n = int(rng.integers(max(n_segments, length - 5), length + 1))
        dirs = rng.normal(size=(n_segments, action_dim)).astype(np.float32)
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        ends = np.sort(rng.choice(np.arange(n - 1), n_segments - 1, replace=False)).tolist() + [n - 1]
        seg = np.searchsorted(np.array(ends), np.arange(n))
        actions = dirs[seg] + 0.05 * rng.normal(size=(n, action_dim)).astype(np.float32)
        pos = np.concatenate([np.zeros((1, action_dim)), np.cumsum(actions, 0)]).astype(np.float32)
        ctx = np.resize(dirs.ravel(), obs_dim - action_dim) if obs_dim > action_dim else np.zeros(0)
        obs = np.concatenate([pos, np.repeat(ctx[None].astype(np.float32), n + 1, 0)], axis=1)[:, :obs_dim]
        episodes.append(Episode(
            obs=obs.astype(np.float32), actions=actions.astype(np.float32), success=np.arange(n) == n - 1,
            episode_id=i, reset_kwargs={"seed": i}, extras={"subskill_ends": np.array(ends, dtype=np.int64)},
        ))
    return TrajectorySet(episodes=episodes, env_info={"env_id": env_id, "env_kwargs": {}, "max_episode_steps": length})
