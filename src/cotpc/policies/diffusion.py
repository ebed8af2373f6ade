"""Diffusion Policy (Chi et al., RSS 2023) as a policy family, at the size the CoTPC paper compared (~1.2M
parameters): a 1-D temporal convolutional U-Net over a chunk of ``pred_horizon`` actions, FiLM-conditioned on the
diffusion step and the last ``obs_horizon`` states, trained as a DDPM (100 steps, squared-cosine schedule,
epsilon prediction) and sampled with DDIM in a few steps. An exponential moving average (EMA) of the weights,
held inside the model as buffers and saved in the checkpoint, is what evaluation and inference use.

A training window (:class:`cotpc.data.dataset.WindowDataset` with ``future_actions``) holds the states s(t-1),
s(t) and the actions a(t-1) .. a(t+14): ``actions`` (the window's a(t-1), a(t)) followed by ``future_actions``;
an episode's start repeats its first state and action, its end its last action, as DP pads. At inference the
sampled chunk's actions a(t) .. a(t+7) are executed (``action_horizon``) before the policy plans again
(:class:`cotpc.policies.policy.Policy` keeps a queue per environment).

The noise schedules are ``diffusers``' (imported when a model is built: importing diffusers takes seconds, and
``cotpc --help`` should not pay for it). Read ManiSkill3's ``examples/baselines/diffusion_policy`` and LeRobot's
diffusion policy for the references this follows.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass
from typing import Literal

import torch
import torch.nn as nn
import torch.nn.functional as F

from cotpc.policies.base import (BaseConfig, Normaliser, average_into, ema_decay, params_as_buffers,
                                 register_family)


@dataclass(frozen=True)
class DPConfig(BaseConfig):
    """Diffusion Policy: U-Net widths, horizons, diffusion and EMA settings, and the optimisation (the DP
    reference's: AdamW, cosine to 0 after 500 warm-up steps, weight decay 1e-6, batch 256; its lr 1e-4 is raised
    to 1e-3, chosen on validation, see ``lr``)."""

    name: str = "dp"
    """Preset name this configuration came from (informational)."""
    lr: float = 1e-3
    """Peak learning rate. The DP reference's 1e-4 is tuned for schedules of hundreds of thousands of iterations;
    at the budgets of this project's studies it barely trains (Stack Cube, 4000 x 64: held-out action error 2.33,
    cube grasped in 5% of validation episodes, against 0.107 and 80% at 1e-3; the maze, 1500 x 64: 1.6 against
    1.07; docs/results). ``--lr 1e-4`` restores the reference."""
    min_lr: float = 0.0
    """Final learning rate of the cosine schedule (DP reference: 0)."""
    schedule: Literal["cosine", "constant"] = "cosine"
    """Learning-rate schedule after the warm-up."""
    warmup_iters: int = 500
    """Linear warm-up iterations (DP reference: 500; capped at a tenth of the run)."""
    batch_size: int = 256
    """Global batch size (DP reference, low-dimensional tasks: 256)."""
    weight_decay: float = 1e-6
    """AdamW weight decay of the Linear (FiLM, step-embedding) matrices (DP reference: 1e-6)."""

    # --- horizons ---
    obs_horizon: int = 2
    """States the policy is conditioned on: s(t-obs_horizon+1) .. s(t)."""
    pred_horizon: int = 16
    """Actions per sampled chunk, from a(t-obs_horizon+1) on."""
    action_horizon: int = 8
    """Actions of a chunk executed before planning again: a(t) .. a(t+action_horizon-1)."""

    # --- the noise-prediction U-Net ---
    down_dims: tuple[int, ...] = (32, 64, 128)
    """Channels of the U-Net levels (the chunk is halved in time between levels). (32, 64, 128) gives the paper's
    ~1.2M parameters: 1.14M on Moving Maze (10-dim states, 2-dim actions), 1.26M at the ManiSkill shape of
    `cotpc bench` (43, 8). DP's own default is (256, 512, 1024), ~65M; ManiSkill3's baseline's (64, 128, 256),
    ~4.4M."""
    step_embed_dim: int = 64
    """Size of the sinusoidal diffusion-step embedding (part of the FiLM condition)."""
    kernel_size: int = 5
    """Temporal kernel of the convolutions."""
    n_groups: int = 8
    """GroupNorm groups."""

    # --- diffusion ---
    train_steps: int = 100
    """DDPM diffusion steps in training (squared-cosine beta schedule, epsilon prediction)."""
    inference_steps: int = 10
    """DDIM steps at inference (any number up to ``train_steps``; read at each call, so it can be changed on a
    loaded policy with ``policy.model.cfg = policy.model.cfg.replace(inference_steps=n)``)."""
    clip_sample: float = 5.0
    """Each denoising step clips its estimate of the clean chunk to +-this many standard deviations of the
    training actions (DP clips to [-1, 1] after min-max scaling; here actions are z-scored). 0: no clipping."""

    # --- EMA of the weights (used for evaluation and inference) ---
    ema_power: float = 0.75
    """EMA warm-up: the decay after k updates is 1 - (1 + k)^-power (DP reference: 0.75)."""
    ema_max_decay: float = 0.9999
    """Largest EMA decay (DP reference: 0.9999)."""

    @property
    def window(self) -> int:
        """Timesteps of states per training window: the observation horizon."""
        return self.obs_horizon

    @property
    def future_actions(self) -> int:
        """Actions after a(t) a training window carries: a(t+1) .. a(t + pred_horizon - obs_horizon)."""
        return self.pred_horizon - self.obs_horizon

    @property
    def action_head(self) -> str:  # read by the reports next to the transformer's heads
        return "diffusion"

    def validate(self) -> None:
        if self.obs_horizon < 1 or self.action_horizon < 1:
            raise ValueError("obs_horizon and action_horizon must be >= 1")
        if self.obs_horizon + self.action_horizon - 1 > self.pred_horizon:
            raise ValueError(f"obs_horizon + action_horizon - 1 = {self.obs_horizon + self.action_horizon - 1} "
                             f"actions do not fit in pred_horizon={self.pred_horizon}")
        if not self.down_dims:
            raise ValueError("down_dims needs at least one level")
        if self.pred_horizon % 2 ** (len(self.down_dims) - 1):
            raise ValueError(f"pred_horizon={self.pred_horizon} must be divisible by 2^{len(self.down_dims) - 1} "
                             f"(the U-Net halves the chunk between its {len(self.down_dims)} levels)")
        if any(d % self.n_groups for d in self.down_dims):
            raise ValueError(f"every width in down_dims={self.down_dims} must be divisible by n_groups={self.n_groups}")
        if self.step_embed_dim % 2 or self.step_embed_dim < 4:
            raise ValueError("step_embed_dim must be even and >= 4")
        if not 1 <= self.inference_steps <= self.train_steps:
            raise ValueError(f"inference_steps={self.inference_steps} must be in [1, train_steps={self.train_steps}]")


# --- the noise-prediction network: a 1-D temporal U-Net with FiLM conditioning -----------------------------------


class StepEmbedding(nn.Module):
    """Sinusoidal embedding of the diffusion step, then an MLP (as DP)."""

    def __init__(self, dim: int):
        super().__init__()
        self.dim = dim
        self.mlp = nn.Sequential(nn.Linear(dim, 4 * dim), nn.Mish(), nn.Linear(4 * dim, dim))

    def forward(self, t: torch.Tensor) -> torch.Tensor:
        half = self.dim // 2
        freqs = torch.exp(-math.log(10000) * torch.arange(half, device=t.device) / (half - 1))
        x = t.float()[:, None] * freqs[None]
        return self.mlp(torch.cat([x.sin(), x.cos()], dim=-1))


def conv_block(c_in: int, c_out: int, kernel: int, groups: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv1d(c_in, c_out, kernel, padding=kernel // 2), nn.GroupNorm(groups, c_out), nn.Mish())


class FiLMResBlock(nn.Module):
    """Two convolutions; between them the condition sets a per-channel scale and bias (FiLM); a residual."""

    def __init__(self, c_in: int, c_out: int, cond_dim: int, kernel: int, groups: int):
        super().__init__()
        self.conv1 = conv_block(c_in, c_out, kernel, groups)
        self.conv2 = conv_block(c_out, c_out, kernel, groups)
        self.film = nn.Sequential(nn.Mish(), nn.Linear(cond_dim, 2 * c_out))
        self.skip = nn.Conv1d(c_in, c_out, 1) if c_in != c_out else nn.Identity()

    def forward(self, x: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        scale, bias = self.film(cond)[:, :, None].chunk(2, dim=1)
        h = self.conv2(scale * self.conv1(x) + bias)
        return h + self.skip(x)


class UNet1D(nn.Module):
    """Noise prediction eps(x_k, k, cond) for a chunk x_k (B, T, p). As DP's ``ConditionalUnet1D``: per level two
    FiLM residual blocks, then a strided convolution halving T (not after the last level); two blocks in the
    middle; on the way up, the skip of the same resolution concatenated, two blocks, a transposed convolution."""

    def __init__(self, action_dim: int, cond_dim: int, cfg: DPConfig):
        super().__init__()
        k, g, dims = cfg.kernel_size, cfg.n_groups, list(cfg.down_dims)
        self.step_embed = StepEmbedding(cfg.step_embed_dim)
        cond = cfg.step_embed_dim + cond_dim
        widths = [action_dim] + dims
        levels = list(zip(widths[:-1], widths[1:]))
        self.down = nn.ModuleList()
        for i, (a, b) in enumerate(levels):
            last = i == len(levels) - 1
            self.down.append(nn.ModuleList([
                FiLMResBlock(a, b, cond, k, g), FiLMResBlock(b, b, cond, k, g),
                nn.Conv1d(b, b, 3, stride=2, padding=1) if not last else nn.Identity(),
            ]))
        self.mid = nn.ModuleList([FiLMResBlock(dims[-1], dims[-1], cond, k, g) for _ in range(2)])
        self.up = nn.ModuleList()
        for a, b in reversed(levels[1:]):  # the first level's skip is not used (as DP)
            self.up.append(nn.ModuleList([
                FiLMResBlock(2 * b, a, cond, k, g), FiLMResBlock(a, a, cond, k, g),
                nn.ConvTranspose1d(a, a, 4, stride=2, padding=1),
            ]))
        self.final = nn.Sequential(conv_block(dims[0], dims[0], k, g), nn.Conv1d(dims[0], action_dim, 1))

    def forward(self, x: torch.Tensor, k: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        c = torch.cat([self.step_embed(k), cond], dim=-1)
        h = x.transpose(1, 2)  # (B, p, T): channels are the action dimensions
        skips = []
        for res1, res2, down in self.down:
            h = res2(res1(h, c), c)
            skips.append(h)
            h = down(h)
        for res in self.mid:
            h = res(h, c)
        for res1, res2, up in self.up:
            h = up(res2(res1(torch.cat([h, skips.pop()], dim=1), c), c))
        return self.final(h).transpose(1, 2)


def make_schedulers(train_steps: int, clip_sample: float):
    """DDPM for training and DDIM (eta 0: deterministic given the initial noise) for sampling, the squared-cosine
    schedule with epsilon prediction, each step's clean estimate clipped to +-``clip_sample`` (0: no clipping).
    Shared by the diffusion families (diffusers is imported here, when a model is built: it takes seconds)."""
    # diffusers takes ~1 s to import: only the diffusion families pay for it, when a model is built
    from diffusers.schedulers.scheduling_ddim import DDIMScheduler
    from diffusers.schedulers.scheduling_ddpm import DDPMScheduler

    schedule = dict(num_train_timesteps=train_steps, beta_schedule="squaredcos_cap_v2",
                    clip_sample=clip_sample > 0, clip_sample_range=clip_sample or 1.0, prediction_type="epsilon")
    return DDPMScheduler(**schedule), DDIMScheduler(**schedule)


@torch.no_grad()
def update_ema(ema: nn.Module, net: nn.Module, updates: torch.Tensor, power: float, max_decay: float) -> None:
    """Move ``ema`` (``net``'s parameters held as buffers) towards ``net`` (:func:`ema_decay`'s rule); counts the
    update in ``updates``."""
    average_into(ema, net, ema_decay(int(updates), power, max_decay))
    updates += 1


class DiffusionPolicy(nn.Module):
    """Diffusion Policy: ``loss`` is the DDPM noise-prediction MSE on a window's action chunk; ``sample`` runs
    DDIM with the EMA weights; ``predict_chunk`` gives the actions to execute (normalised)."""

    # Validation samples a DDIM chain per window: score this many held-out windows, evenly spaced (evaluate_loss),
    # so that validation stays under a tenth of a run (at 1024 windows it took 24-26% of 1500-iteration maze runs,
    # docs/performance.md; `cotpc train --val-windows` overrides it).
    validation_windows = 256

    def __init__(self, cfg: DPConfig, obs_dim: int, action_dim: int, max_timestep: int = 0):
        super().__init__()
        self.cfg, self.obs_dim, self.action_dim = cfg, obs_dim, action_dim
        self.norm = Normaliser(obs_dim, action_dim)
        self.net = UNet1D(action_dim, cfg.obs_horizon * obs_dim, cfg)
        self.ema = params_as_buffers(copy.deepcopy(self.net))  # the averaged weights
        self.register_buffer("ema_updates", torch.zeros((), dtype=torch.int64))
        self.train_scheduler, self.sampler = make_schedulers(cfg.train_steps, cfg.clip_sample)

    @property
    def n_params(self) -> int:
        """Trained parameters (the EMA copy, held as buffers, is not counted)."""
        return sum(p.numel() for p in self.parameters())

    # --- training ---
    def forward(self, batch: dict):
        return self.loss(batch)

    def _chunk(self, batch: dict) -> torch.Tensor:
        """The window's action chunk a(t-obs_horizon+1) .. a(t-obs_horizon+pred_horizon), normalised."""
        if "future_actions" not in batch:
            raise ValueError("Diffusion Policy needs windows with future actions: build the WindowDataset with "
                             f"future_actions=cfg.future_actions ({self.cfg.future_actions})")
        return torch.cat([batch["actions"], batch["future_actions"]], dim=1)

    def _denoise_loss(self, net: nn.Module, batch: dict, generator: torch.Generator | None = None) -> torch.Tensor:
        chunk = self._chunk(batch)
        B, dev = chunk.shape[0], chunk.device
        noise = torch.randn(chunk.shape, generator=generator, device=dev)
        k = torch.randint(self.cfg.train_steps, (B,), generator=generator, device=dev)
        noisy = self.train_scheduler.add_noise(chunk, noise, k)
        pred = net(noisy, k, batch["states"].flatten(1)).float()
        return F.mse_loss(pred, noise)

    def loss(self, batch: dict) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        loss = self._denoise_loss(self.net, batch)  # noise and steps from the global RNG (restored on --resume)
        return loss, {"denoise": loss, "bc": loss, "loss": loss}

    def after_optimizer_step(self) -> None:
        """Move the EMA weights towards the trained ones (the training loop calls this after each step)."""
        update_ema(self.ema, self.net, self.ema_updates, self.cfg.ema_power, self.cfg.ema_max_decay)

    # --- inference ---
    @torch.no_grad()
    def sample(self, states: torch.Tensor, steps: int | None = None,
               generator: torch.Generator | None = None) -> torch.Tensor:
        """Action chunks (B, pred_horizon, p), normalised, for the state histories ``states`` (B, obs_horizon, q),
        normalised: DDIM with the EMA weights from Gaussian noise (``generator``, or torch's global RNG)."""
        B = states.shape[0]
        cond = states.flatten(1).float()
        x = torch.randn((B, self.cfg.pred_horizon, self.action_dim), generator=generator, device=states.device)
        self.sampler.set_timesteps(steps or self.cfg.inference_steps)  # the step indices stay on the CPU
        for k in self.sampler.timesteps.tolist():
            eps = self.ema(x, torch.full((B,), k, device=states.device), cond).float()
            x = self.sampler.step(eps, k, x).prev_sample
        return x

    def predict_chunk(self, states: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        """The actions to execute (B, action_horizon, p), normalised: a(t) .. a(t+action_horizon-1)."""
        start = self.cfg.obs_horizon - 1
        return self.sample(states, generator=generator)[:, start:start + self.cfg.action_horizon]

    def predict(self, batch: dict, generator: torch.Generator | None = None) -> torch.Tensor:
        """The action a(t) (B, p) for the windows' states, normalised."""
        return self.predict_chunk(batch["states"], generator)[:, 0]

    @torch.no_grad()
    def inference_metrics(self, batch: dict) -> dict[str, torch.Tensor]:
        """As the other families: ``action_err`` is the MSE of the sampled a(t) (DDIM, EMA weights) against the
        demo's; ``denoise`` (= ``bc``) the noise-prediction loss of the EMA weights. Both draw their noise from a
        fixed generator, so validation is deterministic and leaves the training RNG alone."""
        gen = torch.Generator(device=batch["states"].device).manual_seed(0)
        denoise = self._denoise_loss(self.ema, batch, gen)
        err = ((self.predict(batch, gen) - batch["actions"][:, -1]) ** 2).mean()
        return {"denoise": denoise, "bc": denoise, "action_err": err}

    @torch.no_grad()
    def validation_metrics(self, batch: dict) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
        """(all-position, last-position) metrics: a window has one prediction, so both are the same."""
        last = self.inference_metrics(batch)
        return {"denoise": last["denoise"], "bc": last["bc"]}, last


register_family("diffusion", DPConfig, DiffusionPolicy, presets={"dp": DPConfig()})  # ~1.2M parameters, as the paper
