"""``cotpc eval RUN --split {seen,unseen}``: batched rollouts with a 95% confidence interval."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Optional

import tyro


@dataclass
class EvalConfig:
    """Roll a trained policy out on Moving Maze configs and report its success rate."""

    run: tyro.conf.Positional[Path]
    """Run directory written by `cotpc train` (config.json + model.safetensors)."""
    split: Literal["seen", "unseen"] = "unseen"
    """seen = the training demos' configs; unseen = the test demos' configs (disjoint seed range)."""
    episodes: Optional[int] = None
    """Evaluate only the first N configs of the split (default: all)."""
    demos: Optional[Path] = None
    """Directory with train.{h5,json} and test.{h5,json} (default: the directory of the run's training data)."""
    checkpoint: Literal["last", "best"] = "last"
    """last = the run's final weights; best = its lowest validation loss (never selected on test success)."""
    video: Optional[Path] = None
    """Write GIFs of the first --num-videos rollouts (agent, blocks and path drawn) into this directory."""
    num_videos: int = 4
    """How many rollouts to record with --video."""
    out: Optional[Path] = None
    """Per-episode results as JSON (default: RUN/eval_<split>.json)."""
    device: str = "cpu"
    """Device for the policy."""


def run_eval(cfg: EvalConfig) -> dict:
    from cotpc import load_policy
    from cotpc.evaluation.maze import evaluate
    from cotpc.policies.policy import read_config

    info = read_config(cfg.run)
    env_id = info.get("dataset", {}).get("env_id", "cotpc/MovingMaze-v0")
    if env_id != "cotpc/MovingMaze-v0":
        raise SystemExit(f"cotpc eval: {cfg.run} was trained on {env_id}; only Moving Maze is supported so far")
    demos = cfg.demos
    if demos is None:
        data_path = info.get("dataset", {}).get("path")
        if not data_path:
            raise SystemExit(f"cotpc eval: {cfg.run}/config.json does not name its data; pass --demos DIR")
        demos = Path(data_path).parent
    weights = cfg.run if cfg.checkpoint == "last" else cfg.run / "best"
    policy = load_policy(weights, device=cfg.device)
    result = evaluate(policy, demos, cfg.split, cfg.episodes, cfg.video, cfg.num_videos)
    result.meta.update({"run": str(cfg.run), "checkpoint": cfg.checkpoint, "demos": str(demos)})
    out = cfg.out or cfg.run / f"eval_{cfg.split}.json"
    result.to_json(out)
    s = result.summary()
    print(
        f"{cfg.run} [{cfg.split}] success {100 * s['success_rate']:.1f}% "
        f"(95% CI {100 * s['ci95'][0]:.1f}-{100 * s['ci95'][1]:.1f}, n={s['episodes']}), "
        f"region transitions {s['mean_region_transitions']:.2f}/5, {s['seconds']:.2f} s -> {out}"
    )
    for v in s.get("videos", []):
        print(f"  video: {v}")
    return s


def main(argv: list[str], prog: str) -> None:
    run_eval(tyro.cli(EvalConfig, args=argv, prog=prog))
