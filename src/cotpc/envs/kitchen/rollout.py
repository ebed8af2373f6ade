"""Evaluation on the ordered Franka Kitchen variant: the paper's two numbers, the success rate (all 4 requested
sub-tasks, in order) and the average number of sub-tasks completed in order per rollout.

A policy is anything with ``reset()`` and ``select_action(obs: (B, 44)) -> (B, 9)``; the configurations of a split
(scene seed and requested order) are read from the demo files and rolled out together: one MuJoCo environment each,
stepped one after another, the policy called once per step for the whole batch.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cotpc.data.trajectories import load_trajectories
from cotpc.envs.kitchen.env import ENV_ID, HORIZON, NUM_REQUESTED, FrankaKitchenOrderedEnv, check_seed, validate_tasks
from cotpc.evaluation.replay import ReplayPolicy  # noqa: F401  (re-exported for the task's replay checks)
from cotpc.evaluation.request import load_for_eval
from cotpc.evaluation.stats import wilson_interval

# Which demo file holds each split's configurations, and the seed range they must come from.
SPLIT_FILES = {"seen": ("train", "train"), "val": ("val", "val"), "unseen": ("test", "test")}


def load_split_configs(demo_dir: str | Path, split: str, episodes: int | None = None) -> list[tuple[int, tuple]]:
    """(seed, requested sub-tasks) of each configuration of ``seen``, ``val`` or ``unseen``."""
    if split not in SPLIT_FILES:
        raise ValueError(f"split must be one of {sorted(SPLIT_FILES)}, got {split!r}")
    name, seed_split = SPLIT_FILES[split]
    path = Path(demo_dir) / f"{name}.h5"
    if not path.exists():
        raise FileNotFoundError(f"no {split} configs: {path} does not exist (cotpc demos kitchen --val/--test N)")
    data = load_trajectories(path, extras=())
    if data.env_info.get("env_id") != ENV_ID:
        raise ValueError(f"{path} holds {data.env_info.get('env_id')!r} demos, not {ENV_ID}")
    configs = []
    for ep in data.episodes[:episodes] if episodes else data.episodes:
        seed = int(ep.reset_kwargs["seed"])
        check_seed(seed, seed_split)  # never evaluate "unseen" on a training scene, or the reverse
        configs.append((seed, validate_tasks(ep.reset_kwargs["options"]["tasks"])))
    return configs


@dataclass
class EvalResult:
    split: str
    success: np.ndarray  # (E,) bool
    completed: np.ndarray  # (E,) sub-tasks completed in order, 0..4
    steps: np.ndarray  # (E,) steps until the episode ended
    seeds: list[int]
    tasks: list[tuple]
    violations: list  # (E,) None or {"task", "reason"}
    seconds: float
    meta: dict = field(default_factory=dict)

    def summary(self) -> dict:
        lo, hi = wilson_interval(int(self.success.sum()), len(self.success))
        return {
            "split": self.split,
            "episodes": len(self.success),
            "success_rate": float(self.success.mean()),
            "ci95": [lo, hi],
            "mean_completed": float(self.completed.mean()),
            "violations": int(sum(v is not None for v in self.violations)),
            "seconds": round(self.seconds, 2),
            **self.meta,
        }

    def to_json(self, path: str | Path) -> None:
        episodes = [{"seed": s, "tasks": list(t), "success": bool(ok), "completed": int(c), "steps": int(n),
                     "violation": v}
                    for s, t, ok, c, n, v in zip(self.seeds, self.tasks, self.success, self.completed, self.steps,
                                                 self.violations)]
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        Path(path).write_text(json.dumps({"summary": self.summary(), "episodes": episodes}, indent=1))


def rollout(policy, configs: list[tuple[int, tuple]], split: str, horizon: int = HORIZON) -> EvalResult:
    """Roll ``policy`` out on every configuration at once."""
    start = time.perf_counter()
    envs = [FrankaKitchenOrderedEnv() for _ in configs]
    obs = np.stack([env.reset(seed=seed, options={"tasks": list(tasks)})[0] for env, (seed, tasks) in zip(envs, configs)])
    policy.reset()
    done = np.zeros(len(envs), dtype=bool)
    steps = np.full(len(envs), horizon)
    infos: list[dict] = [{"success": False, "num_completed": 0, "violation": None} for _ in envs]
    for t in range(horizon):
        actions = np.asarray(policy.select_action(obs))
        for i, env in enumerate(envs):
            if done[i]:
                continue  # a finished episode keeps its last observation
            obs[i], _, terminated, _, infos[i] = env.step(actions[i])
            if terminated:
                done[i], steps[i] = True, t + 1
        if done.all():
            break
    for env in envs:
        env.close()
    return EvalResult(
        split=split,
        success=np.array([info["success"] for info in infos]),
        completed=np.array([info["num_completed"] for info in infos]),
        steps=steps,
        seeds=[seed for seed, _ in configs],
        tasks=[tasks for _, tasks in configs],
        violations=[info["violation"] for info in infos],
        seconds=time.perf_counter() - start,
        meta={"horizon": horizon, "num_requested": NUM_REQUESTED},
    )


def evaluate(policy, demo_dir: str | Path, split: str, episodes: int | None = None,
             horizon: int | None = None) -> EvalResult:
    """Success rate and average completed sub-tasks of ``policy`` on the ``seen``, ``val`` or ``unseen`` configs."""
    return rollout(policy, load_split_configs(demo_dir, split, episodes), split, horizon or HORIZON)


def evaluate_run(req, info: dict, env_id: str) -> dict:
    """``cotpc eval`` of a kitchen run: ``req`` an :class:`cotpc.evaluation.request.EvalRequest`, ``info`` the
    run's config.json. Writes the per-episode JSON and prints the summary."""
    if req.rules not in (None, "paper"):
        raise SystemExit(f"cotpc eval: {env_id} has no rule variants (--rules {req.rules})")
    if req.video:
        raise SystemExit("cotpc eval: --video is not implemented for the kitchen yet")
    demos, weights = req.demos_and_weights(info)
    policy = load_for_eval(weights, req.device, req.sampler_steps)
    result = evaluate(policy, demos, req.split, req.episodes, req.horizon)
    result.meta.update({"run": str(req.run), "checkpoint": req.checkpoint, "demos": str(demos)})
    out = req.out or req.run / f"eval_{req.split}.json"
    result.to_json(out)
    s = result.summary()
    print(f"{req.run} [{req.split}] success {100 * s['success_rate']:.1f}% (95% CI {100 * s['ci95'][0]:.1f}-"
          f"{100 * s['ci95'][1]:.1f}, n={s['episodes']}), completed sub-tasks {s['mean_completed']:.2f}/4, "
          f"{s['seconds']:.1f} s -> {out}")
    return s


