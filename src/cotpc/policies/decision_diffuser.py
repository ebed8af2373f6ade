"""Decision Diffuser (Ajay et al., ICLR 2023) as a policy family, as the CoTPC paper ran it: a diffusion model over
sequences of *states* (100 diffusion steps, context 20, horizon 4) plus an inverse-dynamics MLP that turns two
consecutive states into the action between them; ~1.6M parameters in all.

**What it is conditioned on.** DD conditions its plans on returns (classifier-free guidance) and on the current
state (inpainting). Demonstrations have no rewards, so there is no return conditioning and no guidance: the only
condition is the observed history. A plan is the sequence s(t-19) .. s(t), s(t+1) .. s(t+4) (``history`` +
``horizon`` states); the history part is known and is *imposed* (inpainted), as DD imposes s(t): it replaces the
noisy values before the network sees them in training, and after every denoising step at inference. The network
(a 1-D temporal U-Net over the sequence, conditioned on the diffusion step only) learns the noise of the
``horizon`` future states alone: like DD, which sets the loss weight of its conditioned state to 0, the imposed
positions carry no loss. The action is the inverse dynamics of the current and the first planned state,
a(t) = f(s(t), s_hat(t+1)). Our reading of the paper's "context 20, horizon 4": 20 known states, s(t) included,
and 4 sampled ones after it (in DD's code ``horizon`` is the whole sequence, of which only s(t) is known).

**Padding** (the paper: "we pad the start and end states during training and only the start states during
inference", since DD works on fixed-length sequences). Our reading: in training, a window whose history starts
before its episode repeats the episode's first state s(0) (:class:`cotpc.data.dataset.WindowDataset`), and
one whose future runs past the episode's end repeats its final observation s(N) (``future_states``), so the model
learns to stay at the end of a demonstration; padded future states are diffusion targets like any other. At inference
an episode's first steps repeat s(0) before it (:class:`cotpc.policies.policy.Policy`), as in training; the future
is what is sampled, so there is nothing to pad there. The inverse dynamics trains on every real transition of the
window's history, (s(i), s(i+1)) -> a(i) for i = t-19 .. t (DD trains it on every transition of its sampled
sequence); pairs that start in the padding are left out.

**Acting.** DD executes one action per plan and plans again (``action_horizon`` 1), which makes it the slowest
policy here per control step (a DDIM sampler call each step). ``action_horizon`` k > 1 executes the inverse
dynamics of the planned pairs (s_hat(t+i), s_hat(t+i+1)) for i < k, open loop, through the same per-environment
queue as Diffusion Policy.

**From DD's reference implementation** (``anuragajay/decision-diffuser``): the cosine beta schedule (diffusers'
``squaredcos_cap_v2``, the same formula), epsilon prediction, the loss (diffusion + inverse dynamics) / 2, the
inverse-dynamics MLP (2q -> 256 -> 256 -> p, ReLU), Adam at a constant 2e-4, batch 32 with 2 accumulated steps
(= 64 here), no weight decay. Its temporal U-Net is Janner et al.'s, from which DP's ``ConditionalUnet1D`` derives:
the same levels, blocks, Mish, GroupNorm and kernel 5; it adds the step embedding as a per-channel bias where DP's
FiLM also scales. We reuse DP's U-Net (:class:`cotpc.policies.diffusion.UNet1D`) with the diffusion step as its
only condition, at widths that give the paper's ~1.6M parameters. Changed: data are z-scored (not min-max/CDF
normalised), so each denoising step clips its clean-sequence estimate to +-``clip_sample`` std rather than [-1, 1];
sampling is DDIM in ``inference_steps`` steps from unit Gaussian noise (DD runs all DDPM steps from 0.5-scaled
noise); the EMA is DP's per-step one with DD's averaging horizon (DD updates a 0.995 EMA every 10 steps after
2,000 steps of copying: ~0.9995 a step).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Literal

import torch
import torch.nn as nn
import torch.nn.functional as F

from cotpc.policies.base import BaseConfig, Normaliser, mlp, params_as_buffers, register_family
from cotpc.policies.diffusion import UNet1D, make_schedulers, update_ema


@dataclass(frozen=True)
class DDConfig(BaseConfig):
    """Decision Diffuser: history and horizon of a plan, the U-Net and inverse-dynamics sizes, diffusion and EMA
    settings, and the recommended optimisation (DD's reference: Adam lr 2e-4 constant, effective batch 64, no
    weight decay). The U-Net fields have DP's names because :class:`UNet1D` reads them."""

    name: str = "dd"
    """Preset name this configuration came from (informational)."""
    lr: float = 2e-4
    """Peak learning rate (DD reference: 2e-4)."""
    min_lr: float = 2e-4
    """Final learning rate (unused by the constant schedule)."""
    schedule: Literal["cosine", "constant"] = "constant"
    """Learning-rate schedule after the warm-up (DD reference: constant)."""
    warmup_iters: int = 0
    """Linear warm-up iterations (DD reference: none)."""
    batch_size: int = 64
    """Global batch size (DD reference: 32 with 2 accumulated gradient steps)."""
    weight_decay: float = 0.0
    """AdamW weight decay of the Linear matrices (DD reference: plain Adam)."""

    # --- the plan ---
    history: int = 20
    """Known states a plan starts with, s(t-history+1) .. s(t) (the paper's "context size" 20 for DD, on every
    task; named apart from the transformers' ``context`` so the trainer's task default does not replace it)."""
    horizon: int = 4
    """Future states a plan samples, s(t+1) .. s(t+horizon) (the paper: 4; "longer performs worse")."""
    action_horizon: int = 1
    """Actions executed per plan (DD: 1, planning at every step); k > 1 runs the inverse dynamics of the first k
    planned transitions open loop."""

    # --- the noise-prediction U-Net over the state sequence ---
    down_dims: tuple[int, ...] = (40, 80, 160)
    """Channels of the U-Net levels (the sequence is halved between levels): DD's ``dim`` 40 with ``dim_mults``
    (1, 2, 4), which with the inverse dynamics gives the paper's ~1.6M parameters: 1.67M on Moving Maze (10-dim
    states, 2-dim actions), 1.70M at the ManiSkill shape of `cotpc bench` (43, 8). DD's locomotion setting (dim
    128, mults (1, 4, 8)) would be ~60M."""
    step_embed_dim: int = 40
    """Size of the sinusoidal diffusion-step embedding (DD: ``dim``, the first width)."""
    kernel_size: int = 5
    """Temporal kernel of the convolutions (DD: 5)."""
    n_groups: int = 8
    """GroupNorm groups (DD: 8)."""

    # --- inverse dynamics ---
    inv_hidden: int = 256
    """Hidden width of the inverse-dynamics MLP (s(t), s(t+1)) -> a(t), two hidden layers (DD: 256)."""

    # --- diffusion ---
    train_steps: int = 100
    """DDPM diffusion steps in training (the paper: 100; cosine beta schedule, epsilon prediction)."""
    inference_steps: int = 10
    """DDIM steps at inference (any number up to ``train_steps``; read at each call, so it can be changed on a
    loaded policy with ``policy.model.cfg = policy.model.cfg.replace(inference_steps=n)``)."""
    clip_sample: float = 5.0
    """Each denoising step clips its estimate of the clean sequence to +-this many standard deviations of the
    training states (DD clips to [-1, 1] after its normalisation; here states are z-scored). 0: no clipping."""

    # --- EMA of the weights (used for evaluation and inference) ---
    ema_power: float = 0.75
    """EMA warm-up: the decay after k updates is 1 - (1 + k)^-power (as DP)."""
    ema_max_decay: float = 0.9995
    """Largest EMA decay: DD's 0.995 every 10 steps is ~0.9995 a step."""

    @property
    def window(self) -> int:
        """Timesteps of states per training window: the plan's known history."""
        return self.history

    @property
    def future_states(self) -> int:
        """States after s(t) a training window carries: the plan's horizon."""
        return self.horizon

    @property
    def action_head(self) -> str:  # read by the reports next to the transformer's heads
        return "inverse-dynamics"

    @property
    def plan_length(self) -> int:
        """States in a sampled sequence: history + horizon."""
        return self.history + self.horizon

    def validate(self) -> None:
        if self.history < 1 or self.horizon < 1:
            raise ValueError("history and horizon must be >= 1")
        if not 1 <= self.action_horizon <= self.horizon:
            raise ValueError(f"action_horizon={self.action_horizon} must be in [1, horizon={self.horizon}] "
                             f"(each executed action needs a planned next state)")
        if not self.down_dims:
            raise ValueError("down_dims needs at least one level")
        if self.plan_length % 2 ** (len(self.down_dims) - 1):
            raise ValueError(f"history + horizon = {self.plan_length} must be divisible by "
                             f"2^{len(self.down_dims) - 1} (the U-Net halves the sequence between its "
                             f"{len(self.down_dims)} levels)")
        if any(d % self.n_groups for d in self.down_dims):
            raise ValueError(f"every width in down_dims={self.down_dims} must be divisible by n_groups={self.n_groups}")
        if self.step_embed_dim % 2 or self.step_embed_dim < 4:
            raise ValueError("step_embed_dim must be even and >= 4")
        if not 1 <= self.inference_steps <= self.train_steps:
            raise ValueError(f"inference_steps={self.inference_steps} must be in [1, train_steps={self.train_steps}]")


class DDNet(nn.Module):
    """The two trained networks: the noise-prediction U-Net over state sequences and the inverse dynamics."""

    def __init__(self, cfg: DDConfig, obs_dim: int, action_dim: int):
        super().__init__()
        self.unet = UNet1D(obs_dim, 0, cfg)  # channels are the state dimensions; no condition but the step
        self.inv = mlp([2 * obs_dim, cfg.inv_hidden, cfg.inv_hidden, action_dim])

    def denoise(self, x: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
        """Predicted noise of the state sequences ``x`` (B, L, q) at diffusion steps ``k`` (B,)."""
        return self.unet(x, k, x.new_zeros(x.shape[0], 0))

    def inverse(self, s: torch.Tensor, s_next: torch.Tensor) -> torch.Tensor:
        """The action (.., p) that takes ``s`` to ``s_next`` (.., q each)."""
        return self.inv(torch.cat([s, s_next], dim=-1))


class DecisionDiffuser(nn.Module):
    """Decision Diffuser: ``loss`` is (noise-prediction MSE on the future states + inverse-dynamics MSE) / 2;
    ``sample`` runs DDIM with the EMA weights, the history imposed; ``predict_chunk`` gives the actions to execute
    (normalised)."""

    # Validation samples a DDIM chain per window: score this many held-out windows, evenly spaced (evaluate_loss),
    # so that validation stays under a tenth of a run (at 1024 windows it took 24-26% of 1500-iteration maze runs,
    # docs/performance.md; `cotpc train --val-windows` overrides it).
    validation_windows = 256

    def __init__(self, cfg: DDConfig, obs_dim: int, action_dim: int, max_timestep: int = 0):
        super().__init__()
        self.cfg, self.obs_dim, self.action_dim = cfg, obs_dim, action_dim
        self.norm = Normaliser(obs_dim, action_dim)
        self.net = DDNet(cfg, obs_dim, action_dim)
        self.ema = params_as_buffers(copy.deepcopy(self.net))  # the averaged weights
        self.register_buffer("ema_updates", torch.zeros((), dtype=torch.int64))
        # DD's cosine_beta_schedule is diffusers' squaredcos_cap_v2 (Nichol & Dhariwal, s = 0.008, betas <= 0.999)
        self.train_scheduler, self.sampler = make_schedulers(cfg.train_steps, cfg.clip_sample)

    @property
    def n_params(self) -> int:
        """Trained parameters, U-Net and inverse dynamics (the EMA copy, held as buffers, is not counted)."""
        return sum(p.numel() for p in self.parameters())

    # --- training ---
    def forward(self, batch: dict):
        return self.loss(batch)

    def _plan(self, batch: dict) -> torch.Tensor:
        """The window's state sequence s(t-history+1) .. s(t+horizon) (B, L, q), normalised."""
        if "future_states" not in batch:
            raise ValueError("Decision Diffuser needs windows with future states: build the WindowDataset with "
                             f"future_states=cfg.future_states ({self.cfg.future_states})")
        return torch.cat([batch["states"], batch["future_states"]], dim=1)

    def _denoise_loss(self, net: DDNet, plan: torch.Tensor, generator: torch.Generator | None = None,
                      step: int | None = None) -> torch.Tensor:
        """Noise-prediction MSE on the future part of ``plan``; the history is imposed clean, as at inference.
        The diffusion steps are drawn uniformly, or are all ``step``."""
        B, H, dev = plan.shape[0], self.cfg.history, plan.device
        noise = torch.randn(plan.shape, generator=generator, device=dev)
        if step is None:
            k = torch.randint(self.cfg.train_steps, (B,), generator=generator, device=dev)
        else:
            k = torch.full((B,), step, device=dev)
        noisy = torch.cat([plan[:, :H], self.train_scheduler.add_noise(plan, noise, k)[:, H:]], dim=1)
        pred = net.denoise(noisy, k).float()
        return F.mse_loss(pred[:, H:], noise[:, H:])

    def _inverse_loss(self, net: DDNet, plan: torch.Tensor, batch: dict) -> torch.Tensor:
        """Inverse-dynamics MSE on the history's real transitions (s(i), s(i+1)) -> a(i)."""
        H = self.cfg.history
        pred = net.inverse(plan[:, :H], plan[:, 1:H + 1]).float()
        err = ((pred - batch["actions"]) ** 2).mean(-1)  # (B, H)
        valid = batch.get("valid")
        if valid is None:
            return err.mean()
        return (err * valid).sum() / valid.sum().clamp(min=1)

    def loss(self, batch: dict) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        plan = self._plan(batch)
        denoise = self._denoise_loss(self.net, plan)  # noise and steps from the global RNG (restored on --resume)
        inv = self._inverse_loss(self.net, plan, batch)
        loss = 0.5 * (denoise + inv)  # as DD
        return loss, {"denoise": denoise, "inv": inv, "bc": loss, "loss": loss}

    @torch.no_grad()
    def after_optimizer_step(self) -> None:
        """Move the EMA weights towards the trained ones (the training loop calls this after each step)."""
        update_ema(self.ema, self.net, self.ema_updates, self.cfg.ema_power, self.cfg.ema_max_decay)

    # --- inference ---
    @torch.no_grad()
    def sample(self, states: torch.Tensor, steps: int | None = None,
               generator: torch.Generator | None = None) -> torch.Tensor:
        """State sequences (B, history + horizon, q), normalised, whose first ``history`` states are ``states``
        (B, history, q), normalised: DDIM with the EMA weights from Gaussian noise (``generator``, or torch's
        global RNG), the history imposed before every denoising step."""
        B, H = states.shape[0], self.cfg.history
        states = states.float()
        x = torch.randn((B, self.cfg.plan_length, self.obs_dim), generator=generator, device=states.device)
        self.sampler.set_timesteps(steps or self.cfg.inference_steps)  # the step indices stay on the CPU
        for k in self.sampler.timesteps.tolist():
            x = torch.cat([states, x[:, H:]], dim=1)
            eps = self.ema.denoise(x, torch.full((B,), k, device=states.device)).float()
            x = self.sampler.step(eps, k, x).prev_sample
        return torch.cat([states, x[:, H:]], dim=1)

    def predict_chunk(self, states: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        """The actions to execute (B, action_horizon, p), normalised: the inverse dynamics (EMA weights) of the
        current and planned states, a(t+i) = f(s_hat(t+i), s_hat(t+i+1)) with s_hat(t) = s(t)."""
        plan = self.sample(states, generator=generator)
        s = plan[:, self.cfg.history - 1:]
        n = self.cfg.action_horizon
        return self.ema.inverse(s[:, :n], s[:, 1:n + 1]).float()

    def predict(self, batch: dict, generator: torch.Generator | None = None) -> torch.Tensor:
        """The action a(t) (B, p) for the windows' states, normalised."""
        return self.predict_chunk(batch["states"], generator)[:, 0]

    @torch.no_grad()
    def inference_metrics(self, batch: dict) -> dict[str, torch.Tensor]:
        """As the other families: ``action_err`` is the MSE of the sampled plan's a(t) (DDIM, EMA weights) against
        the demo's; ``state_err`` that of the planned s(t+1); ``inv`` the inverse dynamics' MSE on the demo's own
        (s(t), s(t+1)); ``denoise`` the noise-prediction loss of the EMA weights; ``bc`` the training objective.
        Two diagnostics of the plan: ``copy_err``, the MSE of s(t) itself as a guess of s(t+1), the size of one
        step, against which to read ``state_err`` (the inverse dynamics turns an error of that size into a wrong
        action); and ``denoise_max_noise``, the noise-prediction MSE at the noisiest step, where the noisy future
        is almost the noise itself, so a network that carries its input through scores near 0.
        The noise comes from a fixed generator, so validation is deterministic and leaves the training RNG
        alone."""
        gen = torch.Generator(device=batch["states"].device).manual_seed(0)
        plan, H = self._plan(batch), self.cfg.history
        denoise = self._denoise_loss(self.ema, plan, gen)
        inv = ((self.ema.inverse(plan[:, H - 1], plan[:, H]).float() - batch["actions"][:, -1]) ** 2).mean()
        sampled = self.sample(batch["states"], generator=gen)
        state_err = ((sampled[:, H] - plan[:, H]) ** 2).mean()
        a = self.ema.inverse(sampled[:, H - 1], sampled[:, H]).float()
        err = ((a - batch["actions"][:, -1]) ** 2).mean()
        copy_err = ((plan[:, H - 1] - plan[:, H]) ** 2).mean()
        # after the sampling above, so that the earlier metrics draw the same noise as before they existed
        denoise_max_noise = self._denoise_loss(self.ema, plan, gen, step=self.cfg.train_steps - 1)
        return {"denoise": denoise, "inv": inv, "bc": 0.5 * (denoise + inv), "state_err": state_err,
                "action_err": err, "copy_err": copy_err, "denoise_max_noise": denoise_max_noise}

    @torch.no_grad()
    def validation_metrics(self, batch: dict) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
        """(all-position, last-position) metrics: the training terms, the inverse dynamics over every transition
        of the window's history; and the inference ones, at the window's last position."""
        last = self.inference_metrics(batch)
        inv = self._inverse_loss(self.ema, self._plan(batch), batch)
        return {"denoise": last["denoise"], "inv": inv, "bc": 0.5 * (last["denoise"] + inv)}, last


register_family("decision-diffuser", DDConfig, DecisionDiffuser,
                presets={"dd": DDConfig()})  # ~1.6M parameters, context 20, horizon 4, as the paper
