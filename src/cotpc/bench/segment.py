"""`cotpc bench segment`: our exact batched DP against ruptures' PELT with the paper's cost.

Synthetic trajectories: piecewise-constant action directions (2..8 segments of random length, random unit
direction times a random magnitude in [0.5, 2]) plus i.i.d. Gaussian noise, at a low, medium and high noise
level (a third of the set each), from a fixed seed.

Both methods are scored with the same reference :func:`cotpc.subskills.objective`, which computes J directly
(segment by segment), not through our prefix-sum expansion.
"""

from __future__ import annotations

import json
import math
import os
import statistics
import time
from dataclasses import asdict, dataclass

import numpy as np
import tyro

from cotpc.subskills.discovery import (
    ZERO_MEAN_RTOL,
    check_actions,
    segment_cost,
    unit_actions,
    discover_batch,
    objective,
)

NOISE_LEVELS = {"low": 0.02, "medium": 0.1, "high": 0.5}  # std per component; directions have norm 0.5..2


@dataclass
class Config:
    """Time exact subskill discovery against ruptures' PELT on synthetic piecewise-constant action sequences."""

    num: int = 1000
    """Number of synthetic trajectories (split evenly over the low / medium / high noise levels)."""
    length: int = 200
    """Steps per trajectory."""
    dim: int = 8
    """Action dimension."""
    beta: float = 0.05
    """Penalty per segment (the paper's single-arm value)."""
    min_size: int = 1
    """Minimum segment length (same for both methods)."""
    repeats: int = 5
    """Timed repeats of our batched DP over the whole set (after one untimed warm-up on a few trajectories); the
    median is reported."""
    ruptures_num: int = 100
    """Trajectories run through ruptures (evenly spaced over the set, so all noise levels); its time for the
    whole set is extrapolated from the per-trajectory mean. 0 skips ruptures."""
    verify: int = 20
    """Trajectories (evenly spaced) also solved by a slow reference DP with directly summed segment costs, to
    check that the fast prefix-sum path reaches the same objective."""
    seed: int = 0
    """Seed of the synthetic set."""
    json: bool = False
    """Print the figures as one JSON object instead of a table."""


def synthetic_set(num: int, length: int, dim: int, seed: int = 0) -> tuple[list[np.ndarray], list[str]]:
    """``num`` piecewise-constant-direction action sequences with noise; returns (actions, noise level names)."""
    rng = np.random.default_rng(seed)
    names = list(NOISE_LEVELS)
    actions, levels = [], []
    for k in range(num):
        level = names[k * len(names) // num]
        m = int(rng.integers(2, 9))
        cuts = np.sort(rng.choice(np.arange(1, length), size=min(m - 1, length - 1), replace=False))
        label = np.searchsorted(cuts, np.arange(length), side="right")
        dirs = rng.normal(size=(len(cuts) + 1, dim))
        dirs *= rng.uniform(0.5, 2.0, size=(len(cuts) + 1, 1)) / np.linalg.norm(dirs, axis=1, keepdims=True)
        actions.append(dirs[label] + NOISE_LEVELS[level] * rng.normal(size=(length, dim)))
        levels.append(level)
    return actions, levels


def reference_dp(actions: np.ndarray, beta: float, min_size: int = 1, cost: str = "mean-cosine") -> np.ndarray:
    """Plain O(N^2 p) DP whose segment costs are summed directly (backwards from each end j), not from prefix
    sums; slow, independent numerics, same zero convention. Used to check the fast path."""
    a = check_actions(actions)
    cost_name = cost
    n = len(a)
    u, norms, nonzero = unit_actions(a)
    F = np.full(n + 1, math.inf)
    F[0] = 0.0
    arg = np.zeros(n + 1, dtype=np.int64)
    for j in range(min_size, n + 1):
        # S[i], U[i], ... = sums over actions i..j-1, for i = 0..j-1 (reverse cumulative sums)
        S = np.cumsum(a[:j][::-1], axis=0)[::-1]
        U = np.cumsum(u[:j][::-1], axis=0)[::-1]
        tot = np.cumsum(norms[:j][::-1])[::-1]
        nnz = np.cumsum(nonzero[:j][::-1])[::-1]
        cnt = j - np.arange(j)
        s_norm = np.linalg.norm(S, axis=1)
        zero = s_norm <= ZERO_MEAN_RTOL * tot
        with np.errstate(divide="ignore", invalid="ignore"):
            cost = np.clip(1.0 - np.einsum("ip,ip->i", U, S) / (cnt * s_norm), 0.0, 2.0)
        cost = np.where(zero, nnz / cnt, cost)
        if cost_name == "sum-cosine":
            cost = cost * cnt
        cand = F[: j - min_size + 1] + cost[: j - min_size + 1]
        arg[j] = int(np.argmin(cand))
        F[j] = cand[arg[j]] + beta
    ends, cur = [], n
    while cur > 0:
        ends.append(cur - 1)
        cur = int(arg[cur])
    return np.array(ends[::-1], dtype=np.int64)


RUPTURES_COSTS = ("direct", "prefix")


def ruptures_pelt(actions: np.ndarray, beta: float, min_size: int = 1, impl: str = "direct") -> np.ndarray:
    """ruptures' Pelt (jump=1, pen=beta) with the paper's mean-cosine cost as a custom cost; inclusive ends.

    ``impl="direct"`` evaluates C on the segment's actions, as written in the paper (and as ruptures' own costs
    are written): O(n p) per call. ``impl="prefix"`` uses prefix sums, O(p) per call: the fastest custom cost we
    could write, which favours ruptures. Both follow our zero convention, so the objectives are comparable.
    """
    try:  # ruptures is optional (the [dev] extra): only this comparison needs it
        import ruptures as rpt
        from ruptures.base import BaseCost
        from ruptures.exceptions import NotEnoughPoints
    except ImportError:
        raise SystemExit("ruptures is not installed; `pip install ruptures` (or the project's [dev] extra)") from None

    class CostCosineMean(BaseCost):
        """C(segment) = mean cosine distance of each action to the segment mean."""

        model = "cosine-mean"

        def __init__(self, min_size: int = 1, impl: str = "direct"):
            self.min_size, self.impl = min_size, impl

        def fit(self, signal):
            a = self.signal = np.asarray(signal, dtype=np.float64)  # ruptures reads .signal
            self.u, self.norms, self.nonzero = unit_actions(a)  # "zero action" is decided trajectory-wide
            z = np.zeros((1, a.shape[1]))
            self.ps = np.concatenate([z, np.cumsum(a, axis=0)])
            self.pu = np.concatenate([z, np.cumsum(self.u, axis=0)])
            self.pn = np.concatenate([[0.0], np.cumsum(self.norms)])
            self.pz = np.concatenate([[0.0], np.cumsum(self.nonzero)])
            return self

        def error(self, start, end):
            n = end - start
            if n < self.min_size:
                raise NotEnoughPoints
            if self.impl == "direct":
                sl = slice(start, end)
                return segment_cost(self.u[sl], self.signal[sl], self.norms[sl], self.nonzero[sl])
            s = self.ps[end] - self.ps[start]
            s_norm = math.sqrt(float(s @ s))
            if s_norm <= ZERO_MEAN_RTOL * (self.pn[end] - self.pn[start]):
                return float(self.pz[end] - self.pz[start]) / n
            return min(2.0, max(0.0, 1.0 - float((self.pu[end] - self.pu[start]) @ s) / (n * s_norm)))

    algo = rpt.Pelt(custom_cost=CostCosineMean(min_size=min_size, impl=impl), min_size=min_size, jump=1)
    bkps = algo.fit(np.asarray(actions, dtype=np.float64)).predict(pen=beta)
    return np.asarray(bkps, dtype=np.int64) - 1


def _compare(j_ours: float, j_other: float) -> str:
    tol = 1e-9 * max(1.0, abs(j_ours), abs(j_other))
    if abs(j_ours - j_other) <= tol:
        return "equal"
    return "ours" if j_ours < j_other else "other"


def run(cfg: Config) -> dict:
    actions, levels = synthetic_set(cfg.num, cfg.length, cfg.dim, cfg.seed)
    load = os.getloadavg()[0]  # other processes on the machine slow every timing down
    discover_batch(actions[:8], cfg.beta, cfg.min_size)  # warm-up: torch's lazy initialisation
    times = []
    for _ in range(max(1, cfg.repeats)):
        t0 = time.perf_counter()
        ours = discover_batch(actions, cfg.beta, cfg.min_size)
        times.append(time.perf_counter() - t0)
    ours_s = statistics.median(times)
    j_ours = np.array([objective(a, e, cfg.beta) for a, e in zip(actions, ours)])
    result: dict = {
        "cpu_count": os.cpu_count(),
        "load_avg_1min": load,
        "num": cfg.num,
        "length": cfg.length,
        "dim": cfg.dim,
        "beta": cfg.beta,
        "min_size": cfg.min_size,
        "noise_levels": NOISE_LEVELS,
        "ours_seconds_all": ours_s,
        "ours_seconds_min": min(times),
        "ours_seconds_runs": times,
        "ours_ms_per_traj": 1e3 * ours_s / cfg.num,
        "ours_segments_mean": float(np.mean([len(e) for e in ours])),
    }

    def spaced(k: int) -> list[int]:
        k = min(k, cfg.num)
        return sorted({int(round(x)) for x in np.linspace(0, cfg.num - 1, k)}) if k > 0 else []

    idx = spaced(cfg.verify)
    if idx:
        ref = [reference_dp(actions[k], cfg.beta, cfg.min_size) for k in idx]
        verdicts = [_compare(j_ours[k], objective(actions[k], e, cfg.beta)) for k, e in zip(idx, ref)]
        result["verify"] = {"num": len(idx), **{v: verdicts.count(v) for v in ("equal", "ours", "other")}}

    idx = spaced(cfg.ruptures_num)
    if idx:
        timing, ends_by_impl = {}, {}
        for impl in RUPTURES_COSTS:
            ruptures_pelt(actions[0][:20], cfg.beta, cfg.min_size, impl)  # warm-up: importing ruptures takes ~1 s
            t0 = time.perf_counter()
            rpt_ends = [ruptures_pelt(actions[k], cfg.beta, cfg.min_size, impl) for k in idx]
            per_traj = (time.perf_counter() - t0) / len(idx)
            ends_by_impl[impl] = rpt_ends
            lower = [_compare(j_ours[k], objective(actions[k], e, cfg.beta)) for k, e in zip(idx, rpt_ends)]
            timing[impl] = {
                "lower_objective": {v: lower.count(v) for v in ("equal", "ours", "other")},
                "ms_per_traj": 1e3 * per_traj,
                "seconds_all_extrapolated": per_traj * cfg.num,
                "speedup_per_traj": per_traj / (ours_s / cfg.num),
            }
        rpt_ends = ends_by_impl["direct"]  # the breakdown below is for the paper's form of the cost
        verdicts = [_compare(j_ours[k], objective(actions[k], e, cfg.beta)) for k, e in zip(idx, rpt_ends)]
        by_level = {}
        for level in NOISE_LEVELS:
            sel = [i for i, k in enumerate(idx) if levels[k] == level]
            by_level[level] = {
                "num": len(sel),
                **{v: [verdicts[i] for i in sel].count(v) for v in ("equal", "ours", "other")},
                "ours_segments_mean": float(np.mean([len(ours[idx[i]]) for i in sel])) if sel else None,
                "ruptures_segments_mean": float(np.mean([len(rpt_ends[i]) for i in sel])) if sel else None,
            }
        import ruptures  # optional (the [dev] extra): only when comparing against it

        result["ruptures"] = {
            "version": ruptures.__version__,
            "num": len(idx),
            "cost_impl": timing,
            "lower_objective": {v: verdicts.count(v) for v in ("equal", "ours", "other")},
            "by_noise": by_level,
        }
    return result


def format_table(r: dict) -> str:
    lines = [
        f"synthetic set: {r['num']} trajectories x {r['length']} steps x {r['dim']}-d actions, beta={r['beta']}, "
        f"min_size={r['min_size']}, noise std {r['noise_levels']}; {r['cpu_count']} CPUs, 1-min load average "
        f"{r['load_avg_1min']:.2f} before timing",
        f"ours (exact batched DP): {r['ours_seconds_all']:.3f} s for the whole set (median of "
        f"{len(r['ours_seconds_runs'])} runs: {', '.join(f'{t:.3f}' for t in r['ours_seconds_runs'])}; the first "
        "is the process's first full-size call), "
        f"{r['ours_ms_per_traj']:.3f} ms/trajectory, {r['ours_segments_mean']:.2f} segments on average",
    ]
    if "verify" in r:
        v = r["verify"]
        lines.append(
            f"check against a direct-sum reference DP on {v['num']} trajectories: equal objective on {v['equal']}, "
            f"ours lower on {v['ours']}, reference lower on {v['other']}"
        )
    if "ruptures" in r:
        x = r["ruptures"]
        lo = x["lower_objective"]
        for impl, t in x["cost_impl"].items():
            lines.append(
                f"ruptures Pelt (jump=1), {impl} custom cost: {t['ms_per_traj']:.2f} ms/trajectory over {x['num']} "
                f"trajectories, extrapolated to the whole set {t['seconds_all_extrapolated']:.1f} s; "
                f"ours is {t['speedup_per_traj']:.0f}x faster per trajectory; lower objective: ours on "
                f"{t['lower_objective']['ours']}, ruptures on {t['lower_objective']['other']}, equal on "
                f"{t['lower_objective']['equal']}"
            )
        lines += [
            "",
            f"direct custom cost, by noise level (lower objective: ours {lo['ours']}, ruptures {lo['other']}, "
            f"equal {lo['equal']}):",
            "| noise | trajectories | ours lower | ruptures lower | equal | segments ours | segments ruptures |",
            "|---|---|---|---|---|---|---|",
        ]
        for level, b in x["by_noise"].items():
            if b["num"]:
                lines.append(
                    f"| {level} ({r['noise_levels'][level]}) | {b['num']} | {b['ours']} | {b['other']} | {b['equal']} "
                    f"| {b['ours_segments_mean']:.2f} | {b['ruptures_segments_mean']:.2f} |"
                )
    return "\n".join(lines)


def main(argv: list[str], prog: str = "cotpc bench segment") -> None:
    cfg = tyro.cli(Config, args=argv, prog=prog)
    if cfg.num < 1 or cfg.length < cfg.min_size or cfg.dim < 1:
        raise SystemExit(f"{prog}: need --num >= 1, --dim >= 1 and --length >= --min-size")
    r = run(cfg)
    print(json.dumps({"config": asdict(cfg), **r}, indent=1) if cfg.json else format_table(r))
