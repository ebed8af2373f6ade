"""``cotpc eval RUN --split {seen,val,unseen}``: batched rollouts with a 95% confidence interval."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Optional

import tyro


@dataclass
class EvalConfig:
    """Roll a trained policy out on the seen or unseen configs of its task and report its success rate: Moving
    Maze, or a ManiSkill3 task (success_once and success_at_end over the full horizon, terminations ignored)."""

    run: tyro.conf.Positional[Path]
    """Run directory written by `cotpc train` (config.json + model.safetensors)."""
    split: Literal["seen", "val", "unseen"] = "unseen"
    """seen = the training demos' configs; val = the validation demos' configs (for choosing settings and
    checkpoints; Moving Maze only); unseen = the test demos' configs. The three seed ranges are disjoint."""
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
    rules: Literal["paper", "any-action", "safe-gaps", "forgiving"] = "paper"
    """Moving Maze rules (docs/moving-maze.md): paper = a step into a gap ends the episode as a failure and each
    action component's magnitude is raised to at least 1.5 ("both components in [1.5, 4]"); any-action = deadly
    gaps, any action up to 4; safe-gaps = a step into a gap is blocked, actions in [1.5, 4]; forgiving = both
    relaxed (this project's default before 2026-12)."""
    out: Optional[Path] = None
    """Per-episode results as JSON (default: RUN/eval_<split>.json under the paper's rules, else
    RUN/eval_<split>_<rules>.json)."""
    device: str = "cpu"
    """Device for the policy."""
    horizon: Optional[int] = None
    """ManiSkill3 tasks: steps per episode (default: the paper's, 200 for StackCube-v1 and PegInsertionSide-v1)."""
    procs: int = 1
    """ManiSkill3 tasks on CPU: processes, each with one environment and a copy of the policy."""
    backend: Literal["auto", "cpu", "gpu"] = "auto"
    """ManiSkill3 tasks: 'gpu' = ManiSkill3's GPU-parallel simulation (--num-envs at once, policy on --device),
    'cpu' = process pool; 'auto' = gpu when CUDA is available."""
    num_envs: int = 256
    """ManiSkill3 tasks with --backend gpu: environments simulated at once."""


def _demos_and_weights(cfg: EvalConfig, info: dict) -> tuple[Path, Path]:
    """The demo directory (given, or that of the run's training data) and the checkpoint to evaluate."""
    demos = cfg.demos
    if demos is None:
        data_path = info.get("dataset", {}).get("path")
        if not data_path:
            raise SystemExit(f"cotpc eval: {cfg.run}/config.json does not name its data; pass --demos DIR")
        demos = Path(data_path).parent
    return demos, (cfg.run if cfg.checkpoint == "last" else cfg.run / "best")


def run_eval(cfg: EvalConfig) -> dict:
    from cotpc import load_policy
    from cotpc.envs.moving_maze import ENV_ID as MAZE_ENV_ID
    from cotpc.envs.moving_maze import RULES
    from cotpc.evaluation.maze import eval_name, evaluate
    from cotpc.policies.policy import read_config

    info = read_config(cfg.run)
    env_id = info.get("dataset", {}).get("env_id", MAZE_ENV_ID)
    if env_id != MAZE_ENV_ID:
        from cotpc.envs.maniskill import is_maniskill_env

        if is_maniskill_env(env_id):
            return run_eval_maniskill(cfg, info, env_id)
        raise SystemExit(f"cotpc eval: {cfg.run} was trained on {env_id}; supported: Moving Maze and ManiSkill3 tasks")
    demos, weights = _demos_and_weights(cfg, info)
    policy = load_policy(weights, device=cfg.device)
    rules = RULES[cfg.rules]
    result = evaluate(policy, demos, cfg.split, cfg.episodes, cfg.video, cfg.num_videos, rules.deadly_gaps,
                      rules.min_action)
    result.meta.update({"run": str(cfg.run), "checkpoint": cfg.checkpoint, "demos": str(demos)})
    out = cfg.out or cfg.run / f"eval_{eval_name(cfg.split, rules.deadly_gaps, rules.min_action)}.json"
    result.to_json(out)
    s = result.summary()
    print(
        f"{cfg.run} [{cfg.split}, {cfg.rules} rules] success {100 * s['success_rate']:.1f}% "
        f"(95% CI {100 * s['ci95'][0]:.1f}-{100 * s['ci95'][1]:.1f}, n={s['episodes']}), "
        f"region transitions {s['mean_region_transitions']:.2f}/5, {s['seconds']:.2f} s -> {out}"
    )
    for v in s.get("videos", []):
        print(f"  video: {v}")
    return s


def run_eval_maniskill(cfg: EvalConfig, info: dict, env_id: str) -> dict:
    from cotpc.envs.maniskill import import_maniskill
    from cotpc.evaluation.maniskill import evaluate, policy_loader

    if cfg.rules != "paper":
        raise SystemExit(f"cotpc eval: --rules {cfg.rules} is a Moving Maze option; {cfg.run} was trained on {env_id}")
    import_maniskill()
    if cfg.video:
        raise SystemExit("cotpc eval: --video needs a render device for ManiSkill3 tasks; not supported yet")
    demos, weights = _demos_and_weights(cfg, info)
    device = cfg.device if cfg.backend != "cpu" else "cpu"
    result = evaluate(policy_loader(weights, device), demos, cfg.split, cfg.episodes, horizon=cfg.horizon,
                      procs=cfg.procs, backend=cfg.backend, num_envs=cfg.num_envs)
    if result.env_id != env_id:
        raise SystemExit(f"cotpc eval: {cfg.run} was trained on {env_id} but {demos} holds {result.env_id} demos")
    result.meta.update({"run": str(cfg.run), "checkpoint": cfg.checkpoint, "demos": str(demos)})
    out = cfg.out or cfg.run / f"eval_{cfg.split}.json"
    result.to_json(out)
    s = result.summary()
    lo1, hi1 = s["success_once_ci95"]
    lo2, hi2 = s["success_at_end_ci95"]
    print(
        f"{cfg.run} [{env_id} {cfg.split}, horizon {s['horizon']}] success_once {100 * s['success_once']:.1f}% "
        f"(95% CI {100 * lo1:.1f}-{100 * hi1:.1f}), success_at_end {100 * s['success_at_end']:.1f}% "
        f"(95% CI {100 * lo2:.1f}-{100 * hi2:.1f}), n={s['episodes']}, {s['seconds']:.1f} s ({s['backend']}) -> {out}"
    )
    return s


def main(argv: list[str], prog: str) -> None:
    run_eval(tyro.cli(EvalConfig, args=argv, prog=prog))
