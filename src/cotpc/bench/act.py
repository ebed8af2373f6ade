"""`cotpc bench act`: milliseconds per ``Policy.select_action`` call at batch 1 and batch 100.

A policy that plans a chunk of actions (the diffusion policies) is slow on the step that plans and nearly free on
the others, so each row gives the mean over the timed calls (the cost per control step, amortised over the
executed chunk), the median, the 90th percentile and the worst step (a planning step: what a real-time
controller must budget for). ManiSkill setting (context 10, 43-dim state, 8-dim action, K=128, 128-d, 4 layers, 8 heads), randomly
initialised weights (speed does not depend on them). The context is full (steady state of an episode).
"""

from __future__ import annotations

import json
import statistics
import time
from dataclasses import asdict, dataclass
from typing import Optional

import numpy as np
import torch
import tyro

from cotpc.policies import Policy, get_preset, make_model


@dataclass
class Config:
    """Time select_action of each policy."""

    policies: tuple[str, ...] = ("bc", "dt", "bet", "cotpc", "cotpc-causal", "decoupled", "dp", "dd")
    """Policies to time."""
    batch_sizes: tuple[int, ...] = (1, 100)
    """Numbers of environments acting at once."""
    calls: int = 200
    """Timed calls per policy and batch size (a multiple of a chunk policy's executed actions, so the mean is
    its amortised cost)."""
    threads: Optional[int] = None
    """torch CPU threads (default: torch's)."""
    json: bool = False
    """Print JSON instead of a table."""


def bench(name: str, batch: int, calls: int) -> dict:
    cfg = get_preset(name, context=10, n_centres=128)
    torch.manual_seed(0)
    pol = Policy(make_model(cfg, 43, 8, 200))
    obs = np.random.default_rng(0).normal(size=(batch, 43)).astype(np.float32)
    for _ in range(cfg.window + 5):  # fill the context
        pol.select_action(obs)
    times = []
    for _ in range(calls):
        t = time.perf_counter()
        pol.select_action(obs)
        times.append(time.perf_counter() - t)
    return {"policy": name, "batch": batch, "ms": round(1000 * statistics.median(times), 3),
            "ms_mean": round(1000 * statistics.fmean(times), 3),
            "ms_p90": round(1000 * float(np.percentile(times, 90)), 3), "ms_max": round(1000 * max(times), 3)}


def main(argv: list[str], prog: str = "cotpc bench act") -> None:
    cfg = tyro.cli(Config, args=argv, prog=prog)
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    rows = [bench(p, b, cfg.calls) for p in cfg.policies for b in cfg.batch_sizes]
    if cfg.json:
        print(json.dumps({"config": asdict(cfg), "threads": torch.get_num_threads(), "rows": rows}, indent=1))
        return
    print(f"select_action, ManiSkill setting, {torch.get_num_threads()} threads")
    print(f"{'policy':<12} {'batch':>5} {'mean ms':>9} {'median':>9} {'p90':>9} {'worst':>9}")
    for r in rows:
        print(f"{r['policy']:<12} {r['batch']:>5} {r['ms_mean']:>9.3f} {r['ms']:>9.3f} {r['ms_p90']:>9.3f} "
              f"{r['ms_max']:>9.3f}")
