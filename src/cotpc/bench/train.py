"""`cotpc bench train`: milliseconds per training iteration of every policy, and achieved GFLOP/s.

Settings (paper): ManiSkill (context 10, 43-dim state, 8-dim action, K=128) and Moving Maze (context 20, 10-dim
state, 2-dim action, K=1024); batch 256 (32 for bc), 128-d, 4 layers, 8 heads. Synthetic data of those shapes;
the step is the training loop's own (:func:`cotpc.training.train.train_step`: forward, backward, gradient
clipping, fused AdamW, scheduler). FLOPs per step are counted with ``torch.utils.flop_counter`` and compared
with the measured fp32 and bf16 matmul peaks of this machine.
"""

from __future__ import annotations

import json
import statistics
import time
from contextlib import nullcontext
from dataclasses import asdict, dataclass, field
from typing import Literal, Optional

import numpy as np
import torch
import tyro

SETTINGS = {
    "maniskill": {"context": 10, "obs_dim": 43, "action_dim": 8, "n_centres": 128, "length": 120},
    "maze": {"context": 20, "obs_dim": 10, "action_dim": 2, "n_centres": 1024, "length": 60},
}


@dataclass
class Config:
    """Time one training iteration of each policy (synthetic data of the paper's shapes)."""

    policies: tuple[str, ...] = ()
    """Policies to time (default: all presets)."""
    settings: tuple[Literal["maniskill", "maze"], ...] = ("maniskill", "maze")
    """Task settings."""
    iters: int = 10
    """Timed iterations per policy (the median is reported)."""
    warmup: int = 3
    """Untimed iterations first."""
    bf16: Optional[bool] = None
    """bf16 autocast (default: as training decides, see `cotpc train --help`)."""
    threads: Optional[int] = None
    """torch CPU threads (default: torch's)."""
    json: bool = False
    """Print JSON instead of a table."""


def matmul_peak(dtype: torch.dtype, n: int = 2048, reps: int = 5) -> float:
    """GFLOP/s of an n x n x n matmul in ``dtype`` (best of ``reps``)."""
    a, b = torch.randn(n, n, dtype=dtype), torch.randn(n, n, dtype=dtype)
    a @ b
    best = float("inf")
    for _ in range(reps):
        t = time.perf_counter()
        a @ b
        best = min(best, time.perf_counter() - t)
    return 2 * n**3 / best / 1e9


def bench_policy(name: str, setting: str, cfg: Config, bf16: bool) -> dict:
    from cotpc.data.dataset import Stats, WindowDataset, synthetic_trajectories
    from cotpc.policies import get_preset, make_model
    from cotpc.policies.kmeans import kmeans
    from cotpc.training.train import make_optimizer, train_step

    s = SETTINGS[setting]
    pcfg = get_preset(name, context=s["context"], n_centres=s["n_centres"])
    trajs = synthetic_trajectories(64, s["obs_dim"], s["action_dim"], s["length"], n_segments=4, seed=0)
    obs = np.concatenate([e.obs[:-1] for e in trajs.episodes])
    act = np.concatenate([e.actions for e in trajs.episodes])
    ds = WindowDataset(trajs, list(range(len(trajs))), pcfg.window, Stats.of(obs, act), pcfg.cot_targets)
    torch.manual_seed(0)
    model = make_model(pcfg, s["obs_dim"], s["action_dim"], s["length"] + 1)
    if pcfg.action_head == "bet":
        model.centres.copy_(kmeans(ds.actions, pcfg.n_centres, iters=5))
    optimizer, scheduler = make_optimizer(model, pcfg, 10**6, "cpu")
    autocast = (lambda: torch.autocast("cpu", dtype=torch.bfloat16)) if bf16 else nullcontext
    params = list(model.parameters())
    gen = torch.Generator().manual_seed(0)
    model.train()

    def step():
        train_step(model, params, ds.sample(pcfg.batch_size, gen), optimizer, scheduler, 1.0, autocast)

    for _ in range(cfg.warmup):
        step()
    from torch.utils.flop_counter import FlopCounterMode

    with FlopCounterMode(display=False) as fc:
        step()
    flops = fc.get_total_flops()
    times = []
    for _ in range(cfg.iters):
        t = time.perf_counter()
        step()
        times.append(time.perf_counter() - t)
    ms = 1000 * statistics.median(times)
    return {
        "setting": setting, "policy": name, "ms_per_iter": round(ms, 2), "ms_min": round(1000 * min(times), 2),
        "batch_size": pcfg.batch_size, "context": pcfg.window,
        "params": sum(p.numel() for p in model.parameters()), "gflop_per_iter": round(flops / 1e9, 3),
        "gflops": round(flops / 1e9 / (ms / 1000), 1),
    }


def run(cfg: Config) -> dict:
    from cotpc.policies import PRESETS
    from cotpc.training.train import bf16_is_faster

    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    bf16 = bf16_is_faster("cpu") if cfg.bf16 is None else cfg.bf16
    peaks = {"fp32": round(matmul_peak(torch.float32), 1), "bf16": round(matmul_peak(torch.bfloat16), 1)}
    rows = [bench_policy(p, s, cfg, bf16) for s in cfg.settings for p in (cfg.policies or tuple(PRESETS))]
    for r in rows:
        r["pct_of_peak"] = round(100 * r["gflops"] / peaks["bf16" if bf16 else "fp32"], 1)
    return {"bf16": bf16, "threads": torch.get_num_threads(), "matmul_peak_gflops": peaks, "rows": rows,
            "torch": torch.__version__}


def format_table(r: dict) -> str:
    lines = [f"precision {'bf16 autocast' if r['bf16'] else 'fp32'}, {r['threads']} threads, matmul peak "
             f"fp32 {r['matmul_peak_gflops']['fp32']} / bf16 {r['matmul_peak_gflops']['bf16']} GFLOP/s",
             f"{'setting':<10} {'policy':<13} {'ms/iter':>8} {'min':>8} {'batch':>5} {'T':>3} {'params':>8} "
             f"{'GFLOP/it':>8} {'GFLOP/s':>8} {'% peak':>6}"]
    for x in r["rows"]:
        lines.append(f"{x['setting']:<10} {x['policy']:<13} {x['ms_per_iter']:>8.1f} {x['ms_min']:>8.1f} "
                     f"{x['batch_size']:>5} {x['context']:>3} {x['params']:>8} {x['gflop_per_iter']:>8.2f} "
                     f"{x['gflops']:>8.1f} {x['pct_of_peak']:>6.1f}")
    return "\n".join(lines)


def main(argv: list[str], prog: str = "cotpc bench train") -> None:
    cfg = tyro.cli(Config, args=argv, prog=prog)
    r = run(cfg)
    print(json.dumps({"config": asdict(cfg), **r}, indent=1) if cfg.json else format_table(r))
