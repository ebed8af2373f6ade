"""Training, readable top to bottom (CleanRL style): config -> data -> model -> optimiser -> loop -> checkpoints.

Single process: ``cotpc train --data DATA.h5 --policy cotpc --out runs/x``.
Several processes / GPUs / nodes: ``torchrun --nproc_per_node=N -m cotpc.train --data ...`` (DDP; gloo on CPU,
NCCL on GPU). The global batch is split across processes; rank 0 validates, logs and writes checkpoints.

A run directory holds the latest checkpoint (``config.json`` + ``model.safetensors``), ``training_state.pt``
(model, optimiser, scheduler, RNG states, step: everything ``--resume`` needs), ``best/`` (the checkpoint with
the lowest validation action error at the last window position, as at inference, on held-out demos of the
training file), ``loop_timing.json`` (wall time of each part of the loop) and ``tb/`` (TensorBoard).
With ``--ema-decay`` the saved checkpoints and validation hold an exponential moving average of the weights;
``training_state.pt`` keeps the raw weights as well.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Optional

import numpy as np
import torch
import torch.distributed as dist
import torch.nn as nn
import tyro
from tqdm import tqdm

from cotpc.data.dataset import MissingSubskillsError, Stats, WindowDataset, split_episodes
from cotpc.data.trajectories import TrajectoryFormatError, load_trajectories
from cotpc.envs.spec import task_defaults
from cotpc.policies import PRESETS, get_preset
from cotpc.policies.kmeans import kmeans
from cotpc.policies.base import (BaseConfig, average_into, config_from_dict, config_to_dict, ema_decay, make_model,
                                 params_as_buffers)
from cotpc.policies.policy import CheckpointError, link_checkpoint, load_state, save_checkpoint
from cotpc.training.precision import PrecisionChoice, autocast_for, choose_precision

PolicyName = Literal[tuple(PRESETS)]  # type: ignore[valid-type]


@dataclass
class TrainConfig:
    """Train a policy on a demonstration file."""

    data: Path
    """Trajectory file (NAME.h5 with NAME.json beside it); CoT policies need `cotpc segment` run on it first."""
    policy: PolicyName = "cotpc"  # type: ignore[valid-type]
    """Policy preset: baselines bc/dt/bet/dp (Diffusion Policy), the method cotpc, or one of the paper's ablations."""
    out: Path = Path("runs/train")
    """Run directory (checkpoints, best/, tb/)."""
    iters: int = 20_000
    """Training iterations (the paper: 100K-500K by task; fewer here for a CPU)."""
    seed: int = 0
    """Seed for the train/val split, k-means, initialisation and batch sampling."""
    context: Optional[int] = None
    """Context size T (default: the task's, cotpc.envs.spec.task_defaults, as in the paper)."""
    batch_size: Optional[int] = None
    """Global batch size (default: the preset's: 256; bc 32, dd 64)."""
    lr: Optional[float] = None
    """Peak learning rate (default: the preset's, 5e-4; 1e-3 for bc)."""
    min_lr: Optional[float] = None
    """Final learning rate of the cosine schedule (default 5e-5)."""
    warmup_iters: Optional[int] = None
    """Linear warm-up iterations (default 1000, capped at a tenth of the run)."""
    weight_decay: Optional[float] = None
    """AdamW weight decay of the matrices (default 1e-4; 0 for bc)."""
    n_centres: Optional[int] = None
    """k-means centres K for bet/cotpc (default: the task's, cotpc.envs.spec.task_defaults, as in the paper)."""
    cot_layer: Optional[int] = None
    """Block whose CoT features feed the CoT decoder (default -1, the last)."""
    d_model: Optional[int] = None
    """Embedding size (default 128)."""
    n_layers: Optional[int] = None
    """Transformer blocks (default 4)."""
    n_heads: Optional[int] = None
    """Attention heads (default 8)."""
    dropout: Optional[float] = None
    """Dropout (default 0, as the official code)."""
    use_actions: Optional[bool] = None
    """Feed past actions to the transformer policies, interleaved with the states (default: the preset's, True,
    as the paper's BeT and CoTPC); False conditions on the states alone, as the original BeT."""
    episode_timestep: Optional[bool] = None
    """Give the transformer policies the episode timestep (default: the preset's, True, as the official code);
    False: only the position in the window, so the phase must be read from the states."""
    cot_weight: Optional[float] = None
    """lambda, the weight of the CoT loss (default: the paper's 0.1; ignored by policies without a CoT loss)."""
    offset_from: Optional[Literal["state", "cot", "action"]] = None
    """Policies with the k-means centre + offset head (bet, cotpc, ...): the token the offset regressor reads for
    timestep i (default: the preset's; cotpc's is the i-th CoT token, as the paper; ignored by other heads). Not
    the paper's when changed: e.g. ``state`` lets the CoT tokens only carry the chain of thought."""
    action_chunk: Optional[int] = None
    """Transformer policies: actions predicted per window index, a(i) .. a(i+k-1) (default 1, the paper's; not in
    the paper: Diffusion Policy's action chunks, docs/policies.md)."""
    action_horizon: Optional[int] = None
    """Actions of a predicted chunk executed before predicting again (default: the preset's, 1 for the
    transformers, 8 for dp; at most --action-chunk; `cotpc eval --action-horizon` overrides it at evaluation)."""
    state_noise: float = 0.0
    """Std of Gaussian noise added to the normalised input states of every training window (0 = off; targets stay
    clean): a regulariser against memorising the training configurations through the history."""
    ignore_obs: tuple[int, ...] = ()
    """Observation dimensions (0-based) the policy never sees: normalised to 0 in training, validation and at
    inference alike (their std is stored as infinity in the checkpoint's statistics). For Stack Cube, 16 17 are
    the two finger-joint velocities, which make a finger bouncing off the cube look like a release
    (docs/results/maniskill.md). Default: none."""
    obs_std_floor: float = 0.0
    """Lower bound on each observation dimension's std for normalisation, in the observation's units (0 = off,
    as the paper: only a constant dimension is left unscaled). A near-constant dimension is otherwise scaled by
    1 / std: on Stack Cube cube B's height and tilt (std 1e-5 m, 1e-4) read in the hundreds to thousands once A is
    set down on B, far outside anything trained on (docs/results/maniskill.md). 0.01 suits metres and radians.
    Stored in the checkpoint's statistics, so evaluation normalises alike."""
    boundary_weight: float = 1.0
    """Sample training windows that end within --boundary-radius steps of a boundary between two subskills (from
    `cotpc segment`) this many times as often as the others (1 = uniform, as the paper)."""
    boundary_radius: int = 2
    """Steps either side of a subskill boundary that --boundary-weight covers."""
    grad_clip: float = 0.0
    """Clip the global gradient norm to this value (default 0 = off, as the paper and the official code)."""
    ema_decay: float = 0.0
    """Exponential moving average of the weights, for validation, best/ and every saved checkpoint (the weights
    that are evaluated); training and --resume keep the raw ones. The largest decay (e.g. 0.999; 0 = off, as the
    paper), reached after a warm-up as Diffusion Policy's: min(this, 1 - (1 + k)^-0.75) after k steps. Not for
    the diffusion families, which average their own weights."""
    val_fraction: float = 0.1
    """Fraction of the file's episodes held out for the validation loss (split by episode, seeded)."""
    val_every: int = 1000
    """Validation interval in iterations (also at the end)."""
    val_windows: Optional[int] = None
    """Score at most this many held-out windows, evenly spaced, at each validation (default: the policy family's
    cap: 1024 for the transformers, 256 for the diffusion policies, whose validation samples a denoising chain per
    window; every window for the MLP)."""
    ckpt_every: Optional[int] = None
    """Checkpoint interval in iterations (also at the end). Default: a tenth of the run (at most 5000), or a
    twentieth with --keep-checkpoints (the paper's last-20-checkpoints protocol): a killed run loses at most that."""
    keep_checkpoints: bool = False
    """Also keep every periodic checkpoint under checkpoints/step_N/ (for last-k-checkpoint protocols)."""
    log_every: int = 100
    """TensorBoard / progress-bar update interval."""
    resume: bool = False
    """Continue the run in --out from its training_state.pt (same weights as an uninterrupted run)."""
    device: Literal["auto", "cpu", "cuda"] = "auto"
    """Device (auto: cuda if available)."""
    bf16: Optional[bool] = None
    """bfloat16 autocast of the forward pass (weights stay fp32). Default: on for CUDA; on a CPU, chosen by
    timing this run's own training step in both precisions (printed and stored in config.json)."""
    compile: Literal["off", "default", "reduce-overhead"] = "off"
    """torch.compile the training forward and backward: `reduce-overhead` also replays them as CUDA graphs, for
    GPUs, where a small model's step is bound by kernel launches; `default` fuses kernels only. Off by default: on
    a CPU it did not pay (docs/performance.md). A run resumes only with the setting it started with."""
    threads: Optional[int] = None
    """CPU threads per process (default: torch's; under torchrun on CPU, cores / processes)."""
    progress: bool = True
    """Show a tqdm progress bar."""
    stop_after: Optional[int] = None
    """Stop after this iteration as if killed (testing --resume); the schedule still follows --iters."""


def resolve_device(device: str) -> str:
    """``auto`` -> cuda when available, else cpu; anything else unchanged."""
    return ("cuda" if torch.cuda.is_available() else "cpu") if device == "auto" else device


def _param_groups(model: nn.Module, weight_decay: float) -> list[dict]:
    """Decay only Linear weights; biases, LayerNorms, embeddings and prompt tokens are not decayed."""
    decay, no_decay = [], []
    for module in model.modules():
        for name, p in module.named_parameters(recurse=False):
            (decay if isinstance(module, nn.Linear) and name == "weight" else no_decay).append(p)
    return [{"params": decay, "weight_decay": weight_decay}, {"params": no_decay, "weight_decay": 0.0}]


def _lr_lambda(cfg, iters: int):
    warm = min(cfg.warmup_iters, iters // 10)

    def f(step: int) -> float:
        if step < warm:
            return (step + 1) / warm
        if cfg.schedule == "constant":
            return 1.0
        progress = min(1.0, (step - warm) / max(1, iters - warm))
        return (cfg.min_lr + (cfg.lr - cfg.min_lr) * 0.5 * (1 + math.cos(math.pi * progress))) / cfg.lr

    return f


# The validation metric that selects best/ and draws the learning curves: the predicted action's error at the
# last window position, the one select_action uses (all-position losses reward the CoT target leak).
SELECT_ON = "last_action_err"

# The paper reports the best of 3 runs over the last 20 checkpoints (ManiSkill2; the protocol of Diffusion Policy).
# With --keep-checkpoints a run keeps this many by default, evenly spaced over its schedule.
PROTOCOL_CHECKPOINTS = 20


# The TrainConfig fields that decide how training windows are drawn and which kernels compute the step: a resumed
# run must use the same ones to continue bit for bit (a training state saved before a field existed was trained
# with the field's default).
RESUME_MUST_MATCH = ("state_noise", "boundary_weight", "boundary_radius", "compile", "ema_decay", "ignore_obs",
                     "obs_std_floor")


class SettingsError(ValueError):
    """A flag out of range, or flags that do not fit the data (more k-means centres than training actions)."""


def _read_training_state(path: Path) -> dict:
    """``training_state.pt``, or a CheckpointError naming it when it is cut short or not one of ours."""
    try:
        state = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as e:  # torch raises RuntimeError, EOFError or UnpicklingError by how the file is broken
        raise CheckpointError(f"{path}: cannot resume: not a readable training state ({type(e).__name__}: "
                              f"{str(e).splitlines()[0] if str(e) else ''}); a truncated or foreign file") from None
    keys = ("policy", "dims", "model", "optimizer", "scheduler", "rng", "step", "best_val")
    if not isinstance(state, dict) or any(k not in state for k in keys):
        raise CheckpointError(f"{path}: cannot resume: not a cotpc training state (it needs {', '.join(keys)})")
    return state


def checkpoint_interval(config: TrainConfig) -> int:
    """``--ckpt-every``, or its default: a tenth of the run (at most 5000 iterations), a twentieth when every
    checkpoint is kept."""
    if config.ckpt_every is not None:
        if config.ckpt_every < 1:
            raise SettingsError(f"--ckpt-every must be >= 1, got {config.ckpt_every}")
        return config.ckpt_every
    if config.keep_checkpoints:
        return max(config.iters // PROTOCOL_CHECKPOINTS, 1)
    return max(min(config.iters // 10, 5000), 1)


@torch.no_grad()
def evaluate_loss(model: nn.Module, ds: WindowDataset, autocast, chunk: int | None = None,
                  limit: int | None = None) -> dict[str, float]:
    """Validation metrics over every window of ``ds`` (or ``limit`` of them, default the model's
    ``validation_windows``, evenly spaced; no random CoT mask, dropout off), in ``chunk`` windows
    at a time (default: 256 on a CPU, where the activations of larger chunks fall out of the cache and a pass
    took twice as long at 1024, measured in docs/performance.md; 1024 on an accelerator), in two regimes:

    - ``last_*``: at the last window position, as at inference (:meth:`inference_metrics`): what to select on;
    - ``all_*``: the training loss terms averaged over all window positions (where CoT tokens can see the
      targets of the earlier positions): kept for comparison, never for selection."""
    was_training = model.training
    model.eval()
    sums: dict[str, float] = {}
    chunk = chunk or (256 if torch.device(ds.device).type == "cpu" else 1024)
    # A family whose validation samples (the diffusion policies: a DDIM chain per window) caps the windows it
    # scores: a fixed, evenly spaced subset of every held-out episode, the same at each validation.
    limit = limit or getattr(model, "validation_windows", None)
    every = torch.arange(len(ds), device=ds.device)
    if limit and len(ds) > limit:
        every = torch.linspace(0, len(ds) - 1, limit, device=ds.device).round().long()
    for start in range(0, len(every), chunk):
        ends = every[start:start + chunk]
        batch = ds.windows(ends)
        with autocast():
            metrics, last = model.validation_metrics(batch)
        for prefix, group in (("all_", metrics), ("last_", last)):
            for k, v in group.items():
                sums[prefix + k] = sums.get(prefix + k, 0.0) + float(v) * len(ends)
    model.train(was_training)
    return {k: v / len(every) for k, v in sums.items()}


def loss_gradient_shares(model: nn.Module, batch: dict, autocast) -> dict[str, float]:
    """Gradient norm of each weighted loss term on the shared transformer (the trunk), and its share of their
    sum: whether the CoT loss reaches the trunk at all next to the BC terms. Logged at validation time."""
    gpt = getattr(model, "gpt", None)
    if gpt is None:  # the MLP has no trunk shared between terms
        return {}
    cfg = model.cfg
    trunk = [p for p in gpt.blocks.parameters() if p.requires_grad]
    with autocast():
        _, m = model.loss(batch)
    weights = {"ce": 1.0, "offset": cfg.offset_weight, "cot": cfg.cot_weight, "mse": 1.0, "nll": 1.0}
    terms = {k: weights[k] * m[k] for k in weights if k in m}
    norms = {}
    for i, (k, term) in enumerate(terms.items()):
        grads = torch.autograd.grad(term, trunk, retain_graph=i < len(terms) - 1, allow_unused=True)
        norms[k] = float(torch.sqrt(sum((g.float() ** 2).sum() for g in grads if g is not None)))
    total = sum(norms.values()) or 1.0
    return {**{f"{k}_norm": v for k, v in norms.items()}, **{f"{k}_share": v / total for k, v in norms.items()}}


def probe_precision(model: nn.Module, cfg, ds: WindowDataset, batch_size: int, device: str, grad_clip: float):
    """:func:`choose_precision` on copies of the model and a fresh optimiser, with fixed batches drawn from a
    generator of its own; the global RNG (dropout) is restored after, so the run is the same as with an
    explicit ``--bf16``."""
    probe = copy.deepcopy(model)
    optimizer, scheduler = make_optimizer(probe, cfg, 10**6, device)
    params = list(probe.parameters())
    gen = torch.Generator(device=device if device.startswith("cuda") else "cpu")
    gen.manual_seed(12345)
    rng = _rng_state(gen)
    probe.train()

    def make_step(bf16: bool, batch: int):
        sample, autocast = ds.sample(batch, gen), autocast_for(device, bf16)
        return lambda: train_step(probe, params, sample, optimizer, scheduler, grad_clip, autocast)

    try:
        return choose_precision(make_step, batch_size, device)
    finally:
        _set_rng_state(gen, rng)


def train_step(train_model: nn.Module, params, batch: dict, optimizer, scheduler, grad_clip: float, autocast):
    """One optimisation step; returns (loss, metrics)."""
    with autocast():
        loss, metrics = train_model(batch)  # forward() is the loss, so DDP's gradient hooks fire
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    if grad_clip > 0:
        nn.utils.clip_grad_norm_(params, grad_clip)
    optimizer.step()
    scheduler.step()
    after_step = getattr(getattr(train_model, "module", train_model), "after_optimizer_step", None)
    if after_step is not None:  # e.g. Diffusion Policy's EMA of the weights
        after_step()
    return loss, metrics


class WeightAverage:
    """An exponential moving average of ``model``'s weights in a frozen copy of the model (``self.model``, its
    parameters held as buffers), which validation and checkpoints use. The step count is a host integer, so an
    update never waits on the device."""

    def __init__(self, model: nn.Module, max_decay: float, power: float = 0.75):
        self.model = params_as_buffers(copy.deepcopy(model)).eval()
        self.max_decay, self.power = max_decay, power

    def decay(self, updates: int) -> float:
        """Decay of the update after ``updates`` earlier ones: 0 (a copy) first, then DP's warm-up."""
        return ema_decay(updates, self.power, self.max_decay)

    def update(self, model: nn.Module, updates: int) -> None:
        average_into(self.model, model, self.decay(updates))


def make_optimizer(model: nn.Module, cfg, iters: int, device: str):
    """AdamW with decay / no-decay groups (fused kernel where available) and the warm-up + cosine schedule."""
    fused = device.startswith("cuda") or device == "cpu"
    optimizer = torch.optim.AdamW(_param_groups(model, cfg.weight_decay), lr=cfg.lr, betas=(0.9, 0.95), fused=fused)
    return optimizer, torch.optim.lr_scheduler.LambdaLR(optimizer, _lr_lambda(cfg, iters))


def _rng_state(gen: torch.Generator) -> dict:
    s = {"data": gen.get_state(), "torch": torch.get_rng_state()}
    if torch.cuda.is_available():
        s["cuda"] = torch.cuda.get_rng_state_all()
    return s


def _set_rng_state(gen: torch.Generator, s: dict) -> None:
    gen.set_state(s["data"])
    torch.set_rng_state(s["torch"])
    if "cuda" in s and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(s["cuda"])


def _append_timing(run_dir: Path, segment: dict) -> None:
    """loop_timing.json: one entry per training session of the run (a resumed run adds one), so the wall time of
    each part of the loop, and how a run was spread over sessions, can be read back."""
    path = run_dir / "loop_timing.json"
    segments = json.loads(path.read_text()) if path.exists() else []
    path.write_text(json.dumps(segments + [segment], indent=1))


def train(config: TrainConfig) -> Path:
    """Train and return the run directory. torch's thread count is the caller's again afterwards (``--threads``
    sets it for the run only: a library call must not change what later code in the process runs with)."""
    threads = torch.get_num_threads()
    try:
        return _train(config)
    finally:
        torch.set_num_threads(threads)


def check_settings(config: TrainConfig) -> None:
    """SettingsError naming the first flag out of range (before any data is read)."""
    def at_least(name: str, low: float, strict: bool = False) -> None:
        value = getattr(config, name)  # None: the preset's or the task's default
        if value is not None and not (math.isfinite(value) and (value > low if strict else value >= low)):
            raise SettingsError(f"--{name.replace('_', '-')} must be a finite number {'>' if strict else '>='} "
                                f"{low:g}, got {value}")

    for name in ("iters", "context", "batch_size", "n_centres", "d_model", "n_layers", "n_heads", "val_windows",
                 "threads", "val_every", "log_every", "action_chunk", "action_horizon"):
        at_least(name, 1)
    for name in ("lr", "boundary_weight"):
        at_least(name, 0, strict=True)
    for name in ("min_lr", "warmup_iters", "weight_decay", "cot_weight", "state_noise", "boundary_radius",
                 "grad_clip", "obs_std_floor"):
        at_least(name, 0)
    at_least("stop_after", 1)
    for flag, value in (("--dropout", config.dropout), ("--val-fraction", config.val_fraction),
                        ("--ema-decay", config.ema_decay)):
        if value is not None and not 0 <= value < 1:
            raise SettingsError(f"{flag} must be in [0, 1), got {value}")


def policy_config(config: TrainConfig, env_id: str | None) -> BaseConfig:
    """The policy configuration a run of ``config`` on the task ``env_id`` trains: the preset with the flags and the
    task's defaults applied, or SettingsError naming what does not fit (e.g. ``--policy bet --offset-from cot``).
    Needs no data, so studies call it for every policy before they generate anything."""
    defaults = task_defaults(env_id)
    try:
        return get_preset(
            config.policy,
            context=config.context or defaults.context,
            n_centres=config.n_centres or defaults.n_centres,
            batch_size=config.batch_size, lr=config.lr, min_lr=config.min_lr, warmup_iters=config.warmup_iters,
            weight_decay=config.weight_decay, cot_layer=config.cot_layer, d_model=config.d_model,
            n_layers=config.n_layers, n_heads=config.n_heads, dropout=config.dropout, use_actions=config.use_actions,
            episode_timestep=config.episode_timestep,
            cot_weight=config.cot_weight if PRESETS[config.policy].cot_targets else None,
            offset_from=config.offset_from if PRESETS[config.policy].n_kmeans_centres else None,  # offset head only
            action_chunk=config.action_chunk, action_horizon=config.action_horizon,
        )
    except ValueError as e:  # the preset's own consistency checks (e.g. --d-model not divisible by --n-heads)
        raise SettingsError(f"--policy {config.policy}: {e}") from None


def _train(config: TrainConfig) -> Path:
    check_settings(config)
    ckpt_every = checkpoint_interval(config)
    # --- processes and devices ---
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    local_rank = int(os.environ.get("LOCAL_RANK", "0"))
    device = resolve_device(config.device)
    if device == "cuda":
        device = f"cuda:{local_rank}"
        torch.cuda.set_device(device)
    ddp = world > 1
    if ddp and not dist.is_initialized():
        dist.init_process_group(backend="nccl" if device.startswith("cuda") else "gloo")
    if config.threads:
        torch.set_num_threads(config.threads)
    elif ddp and device == "cpu":
        torch.set_num_threads(max(1, (os.cpu_count() or 1) // int(os.environ.get("LOCAL_WORLD_SIZE", world))))
    main_proc = rank == 0
    run_dir = Path(config.out)

    # --- data ---
    trajs = load_trajectories(config.data)
    env_id = trajs.env_info.get("env_id")
    cfg = policy_config(config, env_id)
    if config.ema_decay and hasattr(cfg, "ema_max_decay"):  # the diffusion families
        raise SettingsError(f"--ema-decay: --policy {config.policy} already averages its own weights "
                            f"(ema_max_decay {cfg.ema_max_decay})")
    if cfg.batch_size % world:
        raise SettingsError(f"batch size {cfg.batch_size} is not divisible by the {world} processes")
    train_eps, val_eps = split_episodes(len(trajs), config.val_fraction, config.seed)
    obs_all = np.concatenate([trajs.episodes[i].obs[:-1] for i in train_eps])
    act_all = np.concatenate([trajs.episodes[i].actions for i in train_eps])
    if cfg.n_kmeans_centres > len(act_all):  # k-means needs a point per centre
        raise SettingsError(f"{config.data}: {cfg.n_kmeans_centres} k-means centres need at least as many training "
                            f"actions; its {len(train_eps)} training episodes hold {len(act_all)}: pass "
                            f"--n-centres {min(128, len(act_all))} or fewer, or more demos")
    bad = [d for d in config.ignore_obs if not 0 <= d < trajs.obs_dim]
    if bad:
        raise SettingsError(f"--ignore-obs {' '.join(map(str, bad))}: {config.data} has {trajs.obs_dim}-dim "
                            f"observations (dimensions 0..{trajs.obs_dim - 1})")
    stats = Stats.of(obs_all, act_all, config.obs_std_floor).ignoring(config.ignore_obs)
    if main_proc and config.obs_std_floor:  # say which dimensions the floor changed
        below = Stats.of(obs_all, act_all).small_obs_std(config.obs_std_floor)
        raised = [d for d in below if d not in config.ignore_obs]
        print(f"{config.policy}: --obs-std-floor {config.obs_std_floor:g} raised the std of observation dimensions "
              f"{raised or 'none'}", flush=True)
    where = str(config.data)
    fut = cfg.future_actions  # action chunks (Diffusion Policy); 0 for the other families
    fut_s = cfg.future_states  # planned states (Decision Diffuser); 0 for the other families
    ds = WindowDataset(trajs, train_eps, cfg.window, stats, cfg.cot_targets, config.seed, device, where, fut, fut_s,
                       config.boundary_weight, config.boundary_radius)
    val_ds = WindowDataset(trajs, val_eps, cfg.window, stats, cfg.cot_targets, config.seed + 1, device, where, fut,
                           fut_s) if len(val_eps) else None
    q, p = trajs.obs_dim, trajs.action_dim
    # One timestep-embedding row per step seen in training (states 0..N-1 of the longest demo): every row gets
    # a gradient, and a rollout that runs past the longest demo reads the last trained row (GPT clamps), never
    # an untrained one (evaluation horizons can be twice the mean demo length).
    max_timestep = max(ep.num_steps for ep in trajs.episodes)

    # --- model (identical on every rank: same seed; DDP also broadcasts rank 0's) ---
    torch.manual_seed(config.seed)
    model = make_model(cfg, q, p, max_timestep)
    model.norm.obs_mean.copy_(stats.obs_mean), model.norm.obs_std.copy_(stats.obs_std)
    model.norm.act_mean.copy_(stats.act_mean), model.norm.act_std.copy_(stats.act_std)
    if cfg.n_kmeans_centres:  # BeT heads: k-means of the normalised training actions, once, saved as a buffer
        model.centres.copy_(kmeans(ds.actions.cpu(), cfg.n_kmeans_centres, seed=config.seed))
    model.to(device)
    optimizer, scheduler = make_optimizer(model, cfg, config.iters, device)
    # batches are sampled on the device (a CUDA generator on a GPU: no host round trip per step)
    gen = torch.Generator(device=device if device.startswith("cuda") else "cpu")
    gen.manual_seed(config.seed * 1000 + rank + 1)
    step, best_val = 0, float("inf")

    meta = {
        "max_timestep": max_timestep,
        "dataset": {"path": str(config.data), "env_id": env_id, "env_info": trajs.env_info,
                    "num_episodes": len(trajs), "train_episodes": len(train_eps),
                    "val_episode_ids": [trajs.episodes[i].episode_id for i in val_eps]},
        "train": {k: (str(v) if isinstance(v, Path) else v) for k, v in dataclasses.asdict(config).items()},
    }
    state_path = run_dir / "training_state.pt"
    if config.resume and state_path.exists():
        state = _read_training_state(state_path)
        saved = config_to_dict(config_from_dict(state["policy"]))  # (states saved before policy families too)
        if saved != config_to_dict(cfg) or state["dims"] != [q, p]:
            diff = {k: (saved.get(k), v) for k, v in config_to_dict(cfg).items() if saved.get(k) != v}
            raise CheckpointError(
                f"{run_dir}: cannot resume: the run was trained with another configuration or data "
                f"(differences (saved, now): {diff or ''} dims {state['dims']} vs {[q, p]})"
            )
        for name in RESUME_MUST_MATCH:  # sampling and kernels: a resumed run must match
            default = TrainConfig.__dataclass_fields__[name].default
            if state.get(name, default) != getattr(config, name):
                raise CheckpointError(f"{run_dir}: cannot resume: the run was trained with --{name.replace('_', '-')} "
                                      f"{state.get(name, default)}, not {getattr(config, name)}")
        load_state(model, state["model"], str(state_path))
        optimizer.load_state_dict(state["optimizer"])
        scheduler.load_state_dict(state["scheduler"])
        _set_rng_state(gen, state["rng"][rank])
        step, best_val = state["step"], state["best_val"]
        if config.bf16 is None:  # keep the run's precision so the resumed run matches the uninterrupted one
            config = dataclasses.replace(config, bf16=state.get("bf16"))
    elif not config.resume and state_path.exists():
        raise FileExistsError(f"{run_dir} already holds a run; pass --resume to continue it or choose another --out")

    average = WeightAverage(model, config.ema_decay) if config.ema_decay else None
    if average is not None and step:
        if state.get("ema") is None:
            raise CheckpointError(f"{state_path}: no averaged weights to resume --ema-decay from")
        load_state(average.model, state["ema"], str(state_path))
    evaluated = average.model if average is not None else model  # what validation and checkpoints see

    local_batch = cfg.batch_size // world
    if config.bf16 is None:
        choice = probe_precision(model, cfg, ds, local_batch, device, config.grad_clip) if main_proc else None
        bf16 = torch.tensor(bool(choice.bf16) if choice else False)
        if ddp:  # every rank must agree
            dist.broadcast(bf16, 0)
        config = dataclasses.replace(config, bf16=bool(bf16))
    else:
        how = "kept from the run being resumed" if config.resume and step else "set by --bf16"
        choice = PrecisionChoice(config.bf16, how)
    meta["train"]["bf16"] = config.bf16
    meta["precision"] = choice.as_dict() if choice else None
    if main_proc:
        print(f"{cfg.name}: {choice.summary()}", file=sys.stderr)
    train_model = nn.parallel.DistributedDataParallel(model) if ddp else model
    if config.compile != "off":  # validation, checkpoints and the precision race use the eager model
        train_model = torch.compile(train_model, mode=config.compile)
    autocast = autocast_for(device, config.bf16)

    writer = None
    if main_proc:
        from torch.utils.tensorboard import SummaryWriter  # imports tensorboard (heavy): the logging process only

        run_dir.mkdir(parents=True, exist_ok=True)
        writer = SummaryWriter(str(run_dir / "tb"), purge_step=step if step else None)

    def checkpoint(at: int, val: dict | None) -> None:
        """Rank 0: weights + config, then the full training state, each written atomically."""
        rng = [_rng_state(gen)]
        if ddp:
            rng = [None] * world
            dist.all_gather_object(rng, _rng_state(gen))
        if not main_proc:
            return
        info = {**meta, "step": at, "val": val}
        save_checkpoint(run_dir, evaluated, info)
        if config.keep_checkpoints:
            link_checkpoint(run_dir, run_dir / "checkpoints" / f"step_{at:07d}")
        state = {"step": at, "best_val": best_val, "policy": config_to_dict(cfg), "dims": [q, p],
                 "model": model.state_dict(), "ema": average.model.state_dict() if average else None,
                 "optimizer": optimizer.state_dict(),
                 "scheduler": scheduler.state_dict(), "rng": rng, "bf16": config.bf16,
                 **{name: getattr(config, name) for name in RESUME_MUST_MATCH}}
        tmp = state_path.with_name(state_path.name + ".tmp")
        torch.save(state, tmp)
        os.replace(tmp, state_path)

    # --- loop ---
    end = config.iters if config.stop_after is None else min(config.iters, config.stop_after)
    bar = None
    if main_proc and config.progress:
        bar = tqdm(total=config.iters, initial=step, desc=f"train {cfg.name}", dynamic_ncols=True, file=sys.stderr)
    t0, start_step, last_val = time.perf_counter(), step, None
    loss_v = float("nan")
    train_model.train()
    params = list(model.parameters())
    # wall time of each part of the loop (on CUDA the step is asynchronous: its time lands where the host
    # next waits, in logging or validation, so these shares are exact on a CPU only)
    parts = dict.fromkeys(("sample", "step", "log", "validate", "checkpoint"), 0.0)
    clock = time.perf_counter()

    def lap(part: str) -> None:
        nonlocal clock
        now = time.perf_counter()
        parts[part] += now - clock
        clock = now

    while step < end:
        batch = ds.sample(local_batch, gen, config.state_noise)
        lap("sample")
        loss, metrics = train_step(train_model, params, batch, optimizer, scheduler, config.grad_clip, autocast)
        if average is not None:
            average.update(model, step)
        step += 1
        lap("step")

        if main_proc and (step % config.log_every == 0 or step == end):
            loss_v = loss.item()
            lr = scheduler.get_last_lr()[0]
            for k, v in metrics.items():
                writer.add_scalar(f"train/{k}", v.item(), step)
            writer.add_scalar("train/lr", lr, step)
            if bar is not None:
                bar.set_postfix(loss=f"{loss_v:.4f}", lr=f"{lr:.2e}", refresh=False)
        if bar is not None:
            bar.update(1)
        lap("log")
        if main_proc and val_ds is not None and (step % config.val_every == 0 or step == config.iters):
            last_val = evaluate_loss(evaluated, val_ds, autocast, limit=config.val_windows)
            for k, v in last_val.items():
                writer.add_scalar(f"val/{k}", v, step)
            for k, v in loss_gradient_shares(model, batch, autocast).items():
                writer.add_scalar(f"grad/{k}", v, step)
            if last_val[SELECT_ON] < best_val:  # held-out action error at inference, never test success
                best_val = last_val[SELECT_ON]
                save_checkpoint(run_dir / "best", evaluated, {**meta, "step": step, "val": last_val})
            lap("validate")
        if step % ckpt_every == 0 or step == end:
            checkpoint(step, last_val)
            lap("checkpoint")

    if bar is not None:
        bar.close()
    if main_proc:
        writer.close()
        secs = time.perf_counter() - t0
        done = step - start_step
        overhead = 1 - parts["step"] / secs if secs > 0 else 0.0
        _append_timing(run_dir, {"from_step": start_step, "to_step": step, "wall_s": round(secs, 3),
                                 "parts_s": {k: round(v, 3) for k, v in parts.items()},
                                 "overhead_share": round(overhead, 4), "bf16": config.bf16,
                                 "device": device, "threads": torch.get_num_threads()})
        val_txt = f", val action error {last_val[SELECT_ON]:.4f} (best {best_val:.4f})" if last_val else ""
        print(f"{cfg.name}: {step}/{config.iters} iters ({done} in {secs:.1f} s, {1000 * secs / max(done, 1):.1f} "
              f"ms/iter, {100 * overhead:.1f}% outside the step), loss {loss_v:.4f}{val_txt} -> {run_dir}")
    if ddp:
        dist.barrier()
    return run_dir


def main(argv: list[str] | None = None, prog: str = "cotpc train") -> None:
    config = tyro.cli(TrainConfig, args=sys.argv[1:] if argv is None else argv, prog=prog)
    try:
        train(config)
    except (MissingSubskillsError, TrajectoryFormatError, CheckpointError, SettingsError, FileExistsError) as e:
        print(f"{prog}: error: {e}", file=sys.stderr)
        raise SystemExit(2)
    finally:
        if dist.is_initialized():
            dist.destroy_process_group()
