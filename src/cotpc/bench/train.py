"""`cotpc bench train`: milliseconds per training iteration of every policy, achieved GFLOP/s, and the ratio to
the official CoTPC architecture timed in the same run.

Settings (paper): ManiSkill (context 10, 43-dim state, 8-dim action, K=128) and Moving Maze (context 20, 10-dim
state, 2-dim action, K=1024), and on request ManiSkill with the official code's context of 60 (``maniskill60``);
batch 256 (32 for bc), 128-d, 4 layers, 8 heads. Synthetic data of those shapes;
the step is the training loop's own (:func:`cotpc.training.train.train_step`: forward, backward, gradient
clipping, fused AdamW, scheduler), in the precision training would choose (:func:`probe_precision`: the step
itself timed in fp32 and bf16). FLOPs per step are counted with ``torch.utils.flop_counter`` and compared with
the measured matmul peak of the precision in use.

``--official PATH`` also times the official architecture (SeanJia/CoTPC ``src/model.py``, loaded from PATH, never
copied here: 2 key-state tokens, MSE action head, its own attention, fp32, its AdamW) at the same batch, context
and width, with the official training step (action MSE + 0.1 x key-state MSE, backward, optimiser step). All
steps of a setting are timed in alternating rounds, so a busy spell of the machine hits them alike.
"""

from __future__ import annotations

import contextlib
import importlib.util
import io
import json
import statistics
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable, Literal, Optional

import numpy as np
import torch
import tyro
from torch.utils.flop_counter import FlopCounterMode

from cotpc.data.dataset import Stats, WindowDataset, synthetic_trajectories
from cotpc.envs.spec import check_flags
from cotpc.policies import PRESETS, get_preset, make_model
from cotpc.policies.kmeans import kmeans
from cotpc.training.precision import PrecisionChoice, autocast_for, cpu_info, synchronize, time_alternating
from cotpc.training.train import make_optimizer, probe_precision, train_step

SETTINGS = {
    "maniskill": {"context": 10, "obs_dim": 43, "action_dim": 8, "n_centres": 128, "length": 120},
    "maze": {"context": 20, "obs_dim": 10, "action_dim": 2, "n_centres": 1024, "length": 60},
    # the official code's ManiSkill2 context (its README: 60 for all five tasks; the paper's text says 10)
    "maniskill60": {"context": 60, "obs_dim": 43, "action_dim": 8, "n_centres": 128, "length": 120},
}


@dataclass
class Config:
    """Time one training iteration of each policy (synthetic data of the paper's shapes)."""

    policies: tuple[str, ...] = ()
    """Policies to time (default: all presets)."""
    settings: tuple[Literal["maniskill", "maze", "maniskill60"], ...] = ("maniskill", "maze")
    """Task settings (maniskill60: ManiSkill with the official code's context of 60 instead of the paper's 10)."""
    rounds: int = 5
    """Alternating timing rounds (each times every policy); the fastest and the median step are reported."""
    iters: int = 2
    """Timed iterations per policy in each round."""
    warmup: int = 2
    """Untimed iterations of each policy first."""
    bf16: Optional[bool] = None
    """bf16 autocast (default: as training decides, per policy: its own step timed in both precisions)."""
    official: Optional[Path] = None
    """The official CoTPC code: its `src/model.py`, or a checkout of github.com/SeanJia/CoTPC. Also time its
    architecture in the same rounds and report our CoTPC step as a multiple of its speed."""
    batch_scales: tuple[int, ...] = (1,)
    """Also time each policy at these multiples of its batch, in the same rounds (samples/s column). Training
    N seeds of a policy as one stacked model does the work of one model at N times the batch, so where a larger
    batch does not raise samples/s, stacking seeds (torch.func) cannot either."""
    compile: tuple[Literal["off", "default", "reduce-overhead"], ...] = ("off",)
    """Time each policy's step under these torch.compile modes (as `cotpc train --compile`), in the same rounds;
    compilation happens in the warm-up and is not timed."""
    device: str = "cpu"
    """Device to time on: cpu, or cuda (the GPU path of training: batches sampled on the device, SDPA's fused
    attention, fused AdamW, bf16 where the GPU supports it)."""
    threads: Optional[int] = None
    """torch CPU threads (default: torch's)."""
    json: bool = False
    """Print JSON instead of a table."""


def matmul_peak(dtype: torch.dtype, n: int = 2048, reps: int = 5, budget_s: float = 0.25, device: str = "cpu") -> float:
    """GFLOP/s of an n x n x n matmul in ``dtype`` (best of ``reps``).

    The size doubles from 256 up to ``n`` only while one matmul takes under ``budget_s``: on a CPU without bf16
    instructions a 2048^3 bf16 matmul takes about a minute (measured 0.3 GFLOP/s on an AVX2 EPYC)."""
    size = 256
    while True:
        a, b = (torch.randn(size, size, dtype=dtype, device=device) for _ in range(2))
        a @ b
        best = float("inf")
        for _ in range(reps):
            synchronize(device)
            t = time.perf_counter()
            a @ b
            synchronize(device)
            best = min(best, time.perf_counter() - t)
        if size >= n or best > budget_s / 8:  # the next size takes 8x longer
            return 2 * size**3 / best / 1e9
        size *= 2


def count_flops(step: Callable[[], object]) -> float:
    with FlopCounterMode(display=False) as fc:
        step()
    return fc.get_total_flops()


def policy_step(name: str, setting: str, bf16: Optional[bool], batch_scale: int = 1, device: str = "cpu",
                compile: str = "off") -> tuple[Callable[[], object], dict]:
    """The training step of policy ``name`` on synthetic data of ``setting``'s shape (its batch times
    ``batch_scale``) on ``device``, eager or through ``torch.compile(mode=compile)``, and facts about it."""
    s = SETTINGS[setting]
    pcfg = get_preset(name, context=s["context"], n_centres=s["n_centres"])
    pcfg = pcfg.replace(batch_size=pcfg.batch_size * batch_scale)
    trajs = synthetic_trajectories(64, s["obs_dim"], s["action_dim"], s["length"], n_segments=4, seed=0)
    obs = np.concatenate([e.obs[:-1] for e in trajs.episodes])
    act = np.concatenate([e.actions for e in trajs.episodes])
    ds = WindowDataset(trajs, list(range(len(trajs))), pcfg.window, Stats.of(obs, act), pcfg.cot_targets,
                       device=device, future_actions=pcfg.future_actions, future_states=pcfg.future_states)
    torch.manual_seed(0)
    model = make_model(pcfg, s["obs_dim"], s["action_dim"], s["length"] + 1)
    if pcfg.n_kmeans_centres:
        model.centres.copy_(kmeans(ds.actions.cpu(), pcfg.n_kmeans_centres, iters=5))
    model.to(device)
    choice = probe_precision(model, pcfg, ds, pcfg.batch_size, device, 1.0) if bf16 is None \
        else PrecisionChoice(bf16, "set by --bf16")
    optimizer, scheduler = make_optimizer(model, pcfg, 10**6, device)
    autocast = autocast_for(device, choice.bf16)
    params = list(model.parameters())
    gen = torch.Generator(device=device).manual_seed(0)
    model.train()

    def step_of(step_model: torch.nn.Module) -> Callable[[], object]:
        return lambda: train_step(step_model, params, ds.sample(pcfg.batch_size, gen), optimizer, scheduler, 1.0,
                                  autocast)

    info = {"batch_size": pcfg.batch_size, "context": pcfg.window, "bf16": choice.bf16,
            "precision": choice.as_dict(), "params": sum(p.numel() for p in model.parameters()),
            "compile": compile, "flops": count_flops(step_of(model))}  # counted on the eager step
    return step_of(model if compile == "off" else torch.compile(model, mode=compile)), info


def load_official(path: Path):
    """Import the official ``src/model.py`` from ``path`` (the file, or a checkout that holds it)."""
    path = Path(path)
    file = path if path.is_file() else path / "src" / "model.py"
    if not file.is_file():
        raise SystemExit(f"cotpc bench train: error: --official {path}: no src/model.py of SeanJia/CoTPC there")
    spec = importlib.util.spec_from_file_location("cotpc_official_model", file)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    if not hasattr(module, "GPTWithCoT"):
        raise SystemExit(f"cotpc bench train: error: {file} has no GPTWithCoT: not the official CoTPC model.py")
    return module


def official_step(module, setting: str, batch_size: int = 256, device: str = "cpu") -> tuple[Callable[[], object], dict]:
    """The official CoTPC training step (its train.py: action MSE + 0.1 x key-state MSE, backward, AdamW step
    with its betas and cosine schedule, no clipping) at ``setting``'s shape, fp32 as the official code trains."""
    s = SETTINGS[setting]
    T, q, p = s["context"], s["obs_dim"], s["action_dim"]
    conf = module.GPTConfig(T, n_layer=4, n_head=8, n_embd=128, model_type="s+a+cot", key_states="ab",
                            key_state_loss="0", max_timestep=s["length"] + 1, embd_pdrop=0.0, resid_pdrop=0.0,
                            attn_pdrop=0.0, cot_decoder="256")
    torch.manual_seed(0)
    with contextlib.redirect_stdout(io.StringIO()):  # it prints its parameter count
        model = module.GPTWithCoT(conf, state_dim=q, action_dim=p).to(device)
    optimizer = model.configure_adamw_optimizers({"init_lr": 5e-4, "weight_decay": 0.0, "beta1": 0.9, "beta2": 0.95})
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda i: 1.0)
    gen = torch.Generator().manual_seed(0)
    states, actions = torch.randn(batch_size, T, q, generator=gen), torch.randn(batch_size, T, p, generator=gen)
    timesteps = torch.randint(0, s["length"] - T, (batch_size, 1), generator=gen)
    key_states = torch.randn(batch_size, 2, q, generator=gen)
    states, actions, timesteps, key_states = (x.to(device) for x in (states, actions, timesteps, key_states))
    model.train()

    def step():
        act_pred, ks_pred = model(states, timesteps, actions)
        loss = ((act_pred - actions) ** 2).mean()
        loss = loss + 0.1 * torch.stack([((k - key_states) ** 2).mean() for k in ks_pred]).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        scheduler.step()

    info = {"batch_size": batch_size, "context": T, "bf16": False, "precision": None,
            "params": sum(x.numel() for x in model.parameters()), "compile": "off", "flops": count_flops(step)}
    return step, info


def bench_setting(setting: str, names: list[str], cfg: Config, official) -> list[dict]:
    """Every policy of one setting (and the official architecture), timed in the same alternating rounds."""
    steps, infos = {}, {}
    if any(k < 1 for k in cfg.batch_scales):
        raise SystemExit(f"cotpc bench train: error: --batch-scales must be >= 1, got {cfg.batch_scales}")
    for name in names:
        for k in sorted(set(cfg.batch_scales)):
            for mode in dict.fromkeys(cfg.compile):
                key = name + ("" if k == 1 else f" x{k}") + ("" if mode == "off" else f" [{mode}]")
                steps[key], infos[key] = policy_step(name, setting, cfg.bf16, k, cfg.device, mode)
    if official is not None:
        steps["official"], infos["official"] = official_step(official, setting, device=cfg.device)
    flops = {name: info.pop("flops") for name, info in infos.items()}
    times = time_alternating(steps, rounds=cfg.rounds, reps=cfg.iters, warmup=cfg.warmup, device=cfg.device)
    rows = []
    for name, ts in times.items():
        ms = 1000 * statistics.median(ts)
        rows.append({"setting": setting, "policy": name, "ms_per_iter": round(ms, 2),
                     "ms_min": round(1000 * min(ts), 2), **infos[name],
                     "samples_per_s": round(infos[name]["batch_size"] / min(ts)),
                     "gflop_per_iter": round(flops[name] / 1e9, 3), "gflops": round(flops[name] / 1e9 / (ms / 1000), 1)})
    if official is not None:
        off = next(r for r in rows if r["policy"] == "official")
        for r in rows:  # > 1: faster than the official architecture; on the fastest step of each
            r["speed_vs_official"] = round(off["ms_min"] / r["ms_min"], 2)
    return rows


def run(cfg: Config) -> dict:
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    if cfg.device not in ("cpu", "cuda") or (cfg.device == "cuda" and not torch.cuda.is_available()):
        raise SystemExit(f"cotpc bench train: error: --device {cfg.device}: choose cpu, or cuda where a GPU is "
                         f"visible (torch.cuda.is_available() is {torch.cuda.is_available()})")
    official = load_official(cfg.official) if cfg.official else None
    n = 8192 if cfg.device == "cuda" else 2048
    peaks = {"fp32": round(matmul_peak(torch.float32, n, device=cfg.device), 1),
             "bf16": round(matmul_peak(torch.bfloat16, n, device=cfg.device), 1)}
    names = list(cfg.policies or PRESETS)
    rows = [r for s in cfg.settings for r in bench_setting(s, names, cfg, official)]
    for r in rows:
        r["pct_of_peak"] = round(100 * r["gflops"] / peaks["bf16" if r["bf16"] else "fp32"], 1)
    gpu = torch.cuda.get_device_name() if cfg.device == "cuda" else None
    return {"cpu": cpu_info(), "gpu": gpu, "device": cfg.device, "threads": torch.get_num_threads(),
            "matmul_peak_gflops": peaks, "rows": rows, "torch": torch.__version__}


def format_table(r: dict) -> str:
    cpu = r["cpu"]
    where = f"GPU {r['gpu']}, " if r.get("gpu") else ""
    lines = [f"{where}CPU {cpu['model']} (flags: {' '.join(cpu['flags']) or 'none of amx/avx512'}), {r['threads']} threads, "
             f"torch {r['torch']}, matmul peak fp32 {r['matmul_peak_gflops']['fp32']} / bf16 "
             f"{r['matmul_peak_gflops']['bf16']} GFLOP/s",
             f"{'setting':<10} {'policy':<16} {'prec':>4} {'ms/iter':>8} {'min':>8} {'batch':>5} {'T':>3} "
             f"{'params':>8} {'GFLOP/it':>8} {'GFLOP/s':>8} {'% peak':>6} {'samples/s':>9} {'x official':>10}"]
    for x in r["rows"]:
        ratio = f"{x['speed_vs_official']:>10.2f}" if "speed_vs_official" in x else f"{'':>10}"
        lines.append(f"{x['setting']:<10} {x['policy']:<16} {'bf16' if x['bf16'] else 'fp32':>4} "
                     f"{x['ms_per_iter']:>8.1f} {x['ms_min']:>8.1f} {x['batch_size']:>5} {x['context']:>3} "
                     f"{x['params']:>8} {x['gflop_per_iter']:>8.2f} {x['gflops']:>8.1f} {x['pct_of_peak']:>6.1f} "
                     f"{x['samples_per_s']:>9}{ratio}")
    for x in r["rows"]:
        if x["precision"] and x["precision"].get("fp32_ms") is not None:
            p = x["precision"]
            lines.append(f"  {x['setting']}/{x['policy']}: {'bf16' if p['bf16'] else 'fp32'} chosen; step at batch "
                         f"{p['batch_size']}: fp32 {p['fp32_ms']:.1f} ms, bf16 {p['bf16_ms']:.1f} ms ({p['how']})")
    return "\n".join(lines)


def main(argv: list[str], prog: str = "cotpc bench train") -> None:
    cfg = tyro.cli(Config, args=argv, prog=prog)
    check_flags(prog, 1, {"--rounds": cfg.rounds, "--iters": cfg.iters, "--threads": cfg.threads})
    check_flags(prog, 0, {"--warmup": cfg.warmup})
    r = run(cfg)
    print(json.dumps({"config": asdict(cfg), **r}, indent=1, default=str) if cfg.json else format_table(r))
