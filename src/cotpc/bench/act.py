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
from typing import Literal, Optional

import numpy as np
import torch
import tyro

from cotpc.envs.spec import check_flags
from cotpc.policies import Policy, get_preset, make_model
from cotpc.training.precision import cpu_info


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
    variants: tuple[Literal["eager", "compiled", "bf16"], ...] = ("eager",)
    """Ways to run the transformer policies' inference, timed in alternating rounds (the ratio is the figure to
    read on a shared machine): ``eager`` (what select_action runs by default), ``compiled`` (``Policy(...,
    compile=True)``, ``cotpc eval --compile``: one ``torch.compile`` graph of the network call, inductor with its
    C++ wrapper; the compile time is reported), ``bf16`` (bf16 autocast)."""
    rounds: int = 1
    """Alternating rounds over the variants (each round times ``calls`` calls per variant; the median of all)."""
    json: bool = False
    """Print JSON instead of a table."""


def bench(name: str, batch: int, calls: int, variants: tuple[str, ...] = ("eager",), rounds: int = 1) -> list[dict]:
    cfg = get_preset(name, context=10, n_centres=128)
    torch.manual_seed(0)
    model = make_model(cfg, 43, 8, 200)
    obs = np.random.default_rng(0).normal(size=(batch, 43)).astype(np.float32)
    runners, extra = {}, {}
    for variant in variants:
        if variant != "eager" and not hasattr(model, "predict_window"):
            continue  # the variants concern the transformer family's network call
        pol = Policy(model, compile=variant == "compiled")  # what `cotpc eval --compile` runs
        if variant == "compiled":
            t = time.perf_counter()
            for _ in range(cfg.window + 5):
                pol.select_action(obs)
            extra[variant] = {"compile_s": round(time.perf_counter() - t, 1)}
        step = pol.select_action
        if variant == "bf16":
            def step(o, pol=pol):
                with torch.autocast("cpu", dtype=torch.bfloat16):
                    return pol.select_action(o)
        for _ in range(cfg.window + 5):  # fill the context
            step(obs)
        runners[variant] = step
    times: dict[str, list[float]] = {v: [] for v in runners}
    for _ in range(rounds):
        for variant, step in runners.items():
            for _ in range(calls):
                t = time.perf_counter()
                step(obs)
                times[variant].append(time.perf_counter() - t)
    return [{"policy": name, "variant": v, "batch": batch, "ms": round(1000 * statistics.median(ts), 3),
             "ms_mean": round(1000 * statistics.fmean(ts), 3),
             "ms_p90": round(1000 * float(np.percentile(ts, 90)), 3), "ms_max": round(1000 * max(ts), 3),
             **extra.get(v, {})} for v, ts in times.items()]


def main(argv: list[str], prog: str = "cotpc bench act") -> None:
    cfg = tyro.cli(Config, args=argv, prog=prog)
    check_flags(prog, 1, {"--calls": cfg.calls, "--rounds": cfg.rounds, "--threads": cfg.threads})
    if min(cfg.batch_sizes, default=0) < 1:
        raise SystemExit(f"{prog}: --batch-sizes must be >= 1, got {' '.join(map(str, cfg.batch_sizes))}")
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    rows = [row for p in cfg.policies for b in cfg.batch_sizes
            for row in bench(p, b, cfg.calls, cfg.variants, cfg.rounds)]
    if cfg.json:
        print(json.dumps({"config": asdict(cfg), "cpu": cpu_info(), "torch": torch.__version__,
                          "threads": torch.get_num_threads(), "rows": rows}, indent=1))
        return
    cpu = cpu_info()
    print(f"select_action, ManiSkill setting, {torch.get_num_threads()} threads, {cpu['model']} "
          f"({' '.join(cpu['flags']) or 'no avx2'})")
    print(f"{'policy':<12} {'variant':<9} {'batch':>5} {'mean ms':>9} {'median':>9} {'p90':>9} {'worst':>9}")
    for r in rows:
        print(f"{r['policy']:<12} {r['variant']:<9} {r['batch']:>5} {r['ms_mean']:>9.3f} {r['ms']:>9.3f} "
              f"{r['ms_p90']:>9.3f} {r['ms_max']:>9.3f}"
              + (f"  (compile {r['compile_s']} s)" if "compile_s" in r else ""))
