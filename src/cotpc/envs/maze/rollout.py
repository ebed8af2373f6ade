"""Batched evaluation on Moving Maze: every configuration of a split rolled out at once.

A policy is anything with ``reset()`` and ``select_action(obs: (B, q)) -> (B, p)``: a trained policy from
:func:`cotpc.load_policy`, or the scripted ones below (used by the tests).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import imageio.v2 as imageio
import numpy as np

from cotpc.data.trajectories import load_trajectories
from cotpc.envs.maze.env import (
    ENV_ID, HORIZON, PAPER_MIN_ACTION, RULES, MazeConfig, MazeRules, MovingMazeBatch, check_seed, render_frame,
)
from cotpc.evaluation.replay import ReplayPolicy  # noqa: F401  (re-exported for the task's replay checks)
from cotpc.evaluation.request import load_for_eval
from cotpc.evaluation.stats import wilson_interval

# Which demo file holds each split's configurations, and the seed range they must come from. "val" configs are
# for choosing settings and checkpoints; "unseen" (test) configs only for the final numbers.
SPLIT_FILES = {"seen": ("train", "train"), "val": ("val", "val"), "unseen": ("test", "test")}


def load_split_configs(demo_dir: str | Path, split: str, episodes: int | None = None) -> tuple[list[MazeConfig], list[int]]:
    """Configs (and their seeds) of ``seen`` (the training demos), ``val`` (the validation demos) or ``unseen``
    (the test demos)."""
    configs, seeds, _ = _load_split(demo_dir, split, episodes)
    return configs, seeds


def _load_split(demo_dir: str | Path, split: str, episodes: int | None) -> tuple[list[MazeConfig], list[int], dict]:
    """Configs, seeds and ``env_kwargs`` (the environment rules the configs were made for) of a split."""
    if split not in SPLIT_FILES:
        raise ValueError(f"split must be one of {sorted(SPLIT_FILES)}, got {split!r}")
    name, seed_split = SPLIT_FILES[split]
    if not (Path(demo_dir) / f"{name}.h5").exists():
        hint = " (generate them with `cotpc demos maze --val N`)" if split == "val" else ""
        raise FileNotFoundError(f"no {split} configs: {Path(demo_dir) / f'{name}.h5'} does not exist{hint}")
    data = load_trajectories(Path(demo_dir) / f"{name}.h5", extras=())
    if data.env_info.get("env_id") != ENV_ID:
        raise ValueError(f"{demo_dir}/{name}.json is for {data.env_info.get('env_id')!r}, not Moving Maze")
    chosen = data.episodes[:episodes] if episodes else data.episodes
    configs, seeds = [], []
    for ep in chosen:
        seed = int(ep.reset_kwargs["seed"])
        check_seed(seed, seed_split)  # never evaluate "unseen" on a training config, or the reverse
        configs.append(MazeConfig.from_dict(ep.reset_kwargs["options"]["config"]))
        seeds.append(seed)
    return configs, seeds, data.env_info.get("env_kwargs", {})


def eval_name(split: str, deadly_gaps: bool = True, min_action: float = PAPER_MIN_ACTION) -> str:
    """The name of an evaluation under these rules, as in ``eval_<name>.json``: the split under the paper's
    rules (``unseen``), else the split and the rules' name (``unseen_forgiving``, ``val_any-action``)."""
    rules = MazeRules(deadly_gaps, float(min_action)).name
    return split if rules == "paper" else f"{split}_{rules}"


@dataclass
class EvalResult:
    split: str
    success: np.ndarray  # (E,) bool
    region_transitions: np.ndarray  # (E,) int, 0..5
    steps: np.ndarray  # (E,) steps taken (to success, or the horizon)
    seeds: list[int]
    seconds: float
    meta: dict = field(default_factory=dict)
    fall_points: np.ndarray | None = None  # (E, 2) where the step into a gap would have landed; NaN if none

    @property
    def success_rate(self) -> float:
        return float(self.success.mean())

    def summary(self) -> dict:
        lo, hi = wilson_interval(int(self.success.sum()), len(self.success))
        return {
            "split": self.split,
            "episodes": len(self.success),
            "success_rate": self.success_rate,
            "ci95": [lo, hi],
            "mean_region_transitions": float(self.region_transitions.mean()),
            "seconds": round(self.seconds, 3),
            **self.meta,
        }

    def to_json(self, path: str | Path) -> None:
        episodes = [
            {"seed": s, "success": bool(ok), "region_transitions": int(r), "steps": int(n)}
            for s, ok, r, n in zip(self.seeds, self.success, self.region_transitions, self.steps)
        ]
        if self.fall_points is not None:  # where an episode ended in a gap, as (x, y): what the policy got wrong
            for episode, point in zip(episodes, self.fall_points):
                if not np.isnan(point).any():
                    episode["fell_at"] = [round(float(v), 2) for v in point]
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        Path(path).write_text(json.dumps({"summary": self.summary(), "episodes": episodes}, indent=1))


def rollout(
    policy,
    configs: list[MazeConfig],
    seeds: list[int],
    split: str,
    horizon: int = HORIZON,
    record: int = 0,
    deadly_gaps: bool = True,
    landing: str = "observed",
    min_action: float = PAPER_MIN_ACTION,
) -> tuple[EvalResult, list[list[np.ndarray]]]:
    """Roll ``policy`` out in all ``configs`` at once. Returns the result and, for the first ``record`` episodes,
    the agent positions and block states needed to draw them."""
    start = time.perf_counter()
    env = MovingMazeBatch(configs, horizon=horizon, deadly_gaps=deadly_gaps, landing=landing, min_action=min_action)
    obs = env.reset()
    policy.reset()
    steps = np.full(len(configs), horizon)
    frames: list[list[np.ndarray]] = [[env.state()[i].copy()] for i in range(record)]
    for t in range(horizon):
        actions = np.asarray(policy.select_action(obs))
        was_done = env.success.copy()
        obs, success, done = env.step(actions)
        steps[success & ~was_done] = t + 1
        for i in range(record):
            frames[i].append(env.state()[i].copy())
        if done.all():
            break
    result = EvalResult(
        split=split,
        success=env.success.copy(),
        region_transitions=env.progress.copy(),
        steps=steps,
        seeds=list(seeds),
        fall_points=env.fall_point.copy(),
        seconds=time.perf_counter() - start,
        meta={"deadly_gaps": deadly_gaps, "landing": landing, "min_action": min_action, "fell": int(env.fallen.sum())},
    )
    if min_action:  # how often the policy wanted a smaller move than the rule allows
        result.meta["raised_share"] = env.raised_components / max(env.active_components, 1)
    return result, frames


def write_videos(frames: list[list[np.ndarray]], seeds: list[int], success: np.ndarray, out_dir: str | Path) -> list[Path]:
    """One GIF per recorded episode: agent, blocks and the path so far."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for i, states in enumerate(frames):
        states = np.array(states)
        images = [
            render_frame(s[0:2], s[2], s[3:6], scale=3, path=states[: k + 1, 0:2]) for k, s in enumerate(states)
        ]
        path = out_dir / f"seed{seeds[i]}_{'success' if success[i] else 'fail'}.gif"
        imageio.mimsave(path, images, duration=0.1, loop=0)
        paths.append(path)
    return paths


def evaluate(
    policy,
    demo_dir: str | Path,
    split: str,
    episodes: int | None = None,
    video_dir: str | Path | None = None,
    num_videos: int = 4,
    deadly_gaps: bool = True,
    min_action: float = PAPER_MIN_ACTION,
) -> EvalResult:
    """Success rate of ``policy`` on the ``seen``, ``val`` or ``unseen`` Moving Maze configs of ``demo_dir``.

    The rules default to the paper's (:class:`cotpc.envs.maze.env.MazeRules`): ``deadly_gaps``, a step into
    a gap ends the episode as a failure (False: it is blocked); ``min_action``, every action component's
    magnitude is raised to at least this (0: any action)."""
    configs, seeds, env_kwargs = _load_split(demo_dir, split, episodes)
    landing = env_kwargs.get("landing", "observed")  # the rule the demos were planned for
    record = min(num_videos, len(configs)) if video_dir else 0
    result, frames = rollout(policy, configs, seeds, split, record=record, deadly_gaps=deadly_gaps, landing=landing,
                             min_action=min_action)
    if video_dir:
        result.meta["videos"] = [str(p) for p in write_videos(frames, seeds, result.success, video_dir)]
    return result


def evaluate_run(req, info: dict, env_id: str) -> dict:
    """``cotpc eval`` of a Moving Maze run: ``req`` an :class:`cotpc.evaluation.request.EvalRequest`, ``info`` the
    run's config.json. Writes the per-episode JSON and prints the summary."""
    rules_name = req.rules or "paper"
    if rules_name not in RULES:
        raise SystemExit(f"cotpc eval: unknown Moving Maze rules {rules_name!r}; expected one of {', '.join(RULES)}")
    rules = RULES[rules_name]
    demos, weights = req.demos_and_weights(info)
    policy = load_for_eval(weights, req.device, req.inference_overrides(), compile=req.compile)
    result = evaluate(policy, demos, req.split, req.episodes, req.video, req.num_videos, rules.deadly_gaps,
                      rules.min_action)
    result.meta.update({"run": str(req.run), "checkpoint": req.checkpoint, "demos": str(demos),
                        **req.inference_settings()})
    name = eval_name(req.split, rules.deadly_gaps, rules.min_action)
    out = req.out or req.run / f"eval_{name}{req.variant_suffix()}.json"
    result.to_json(out)
    s = result.summary()
    print(
        f"{req.run} [{req.split}, {rules_name} rules] success {100 * s['success_rate']:.1f}% "
        f"(95% CI {100 * s['ci95'][0]:.1f}-{100 * s['ci95'][1]:.1f}, n={s['episodes']}), "
        f"region transitions {s['mean_region_transitions']:.2f}/5, {s['seconds']:.2f} s -> {out}"
    )
    for v in s.get("videos", []):
        print(f"  video: {v}")
    return s


class RandomPolicy:
    """Uniform random displacements in [-4, 4]^2 (a floor for the success rate)."""

    def __init__(self, seed: int = 0):
        self.seed = seed

    def reset(self) -> None:
        self.rng = np.random.default_rng(self.seed)

    def select_action(self, obs: np.ndarray) -> np.ndarray:
        return self.rng.uniform(-4, 4, size=(len(obs), 2))
