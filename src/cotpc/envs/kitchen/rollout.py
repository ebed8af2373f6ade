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

import imageio.v2 as imageio
import numpy as np
from PIL import Image, ImageDraw  # pillow: imageio's own dependency

from cotpc.data.trajectories import load_trajectories
from cotpc.envs.kitchen.env import ENV_ID, HORIZON, NUM_REQUESTED, FrankaKitchenOrderedEnv, check_seed, validate_tasks
from cotpc.evaluation.replay import ReplayPolicy  # noqa: F401  (re-exported for the task's replay checks)
from cotpc.evaluation.request import load_for_eval
from cotpc.evaluation.stats import wilson_interval

FRAME_EVERY = 4  # record every 4th control step (0.32 s of simulated time) in videos

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
    frames: list = field(default_factory=list, repr=False)  # per recorded rollout: (image, info, step) per frame

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


def rollout(policy, configs: list[tuple[int, tuple]], split: str, horizon: int = HORIZON,
            videos: int = 0, video_size: int = 192, frame_every: int = FRAME_EVERY) -> EvalResult:
    """Roll ``policy`` out on every configuration at once. The first ``videos`` environments render a
    ``video_size`` square frame every ``frame_every`` steps and at their last step (kept in ``EvalResult.frames``,
    captioned by :func:`write_videos`): offscreen MuJoCo rendering without a GPU costs about 0.1-1 s a frame here,
    more than the simulation."""
    start = time.perf_counter()
    envs = [FrankaKitchenOrderedEnv(render_mode="rgb_array" if i < videos else None, width=video_size,
                                    height=video_size) for i in range(len(configs))]
    obs = np.stack([env.reset(seed=seed, options={"tasks": list(tasks)})[0] for env, (seed, tasks) in zip(envs, configs)])
    policy.reset()
    done = np.zeros(len(envs), dtype=bool)
    steps = np.full(len(envs), horizon)
    infos: list[dict] = [{"success": False, "num_completed": 0, "completed": [], "violation": None} for _ in envs]
    frames = [[(envs[i].render(), infos[i], 0)] for i in range(min(videos, len(envs)))]  # (image, info, step)
    for t in range(horizon):
        actions = np.asarray(policy.select_action(obs))
        for i, env in enumerate(envs):
            if done[i]:
                continue  # a finished episode keeps its last observation
            obs[i], _, terminated, _, infos[i] = env.step(actions[i])
            if terminated:
                done[i], steps[i] = True, t + 1
            if i < len(frames) and ((t + 1) % frame_every == 0 or done[i] or t + 1 == horizon):
                frames[i].append((env.render(), infos[i], t + 1))
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
        frames=frames,
    )


def caption(image: np.ndarray, tasks: tuple, info: dict, step: int) -> np.ndarray:
    """``image`` with the requested order above it, each sub-task marked when done (in order), and the outcome."""
    done = list(info.get("completed", []))
    lines = [f"step {step}  " + ("SUCCESS" if info.get("success") else
                                 f"stopped: {info['violation']['task']}" if info.get("violation") else "")]
    lines += [f"{k + 1}. {task}" + ("  [done]" if task in done else "") for k, task in enumerate(tasks)]
    pad = 12 * len(lines) + 6
    canvas = Image.new("RGB", (image.shape[1], image.shape[0] + pad), (255, 255, 255))
    canvas.paste(Image.fromarray(image), (0, pad))
    draw = ImageDraw.Draw(canvas)
    for k, line in enumerate(lines):
        colour = (0, 120, 0) if "[done]" in line or "SUCCESS" in line else (0, 0, 0)
        draw.text((4, 3 + 12 * k), line, fill=colour)
    return np.asarray(canvas)


def write_videos(result: "EvalResult", out_dir: str | Path) -> list[Path]:
    """One captioned GIF per recorded rollout: ``seed<S>_<success|fail>_<completed>of4.gif``."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for i, frames in enumerate(result.frames):
        images = [caption(image, result.tasks[i], info, step) for image, info, step in frames]
        images += [images[-1]] * 8  # hold the last frame
        path = out_dir / (f"seed{result.seeds[i]}_{'success' if result.success[i] else 'fail'}_"
                          f"{int(result.completed[i])}of{NUM_REQUESTED}.gif")
        imageio.mimsave(path, images, duration=0.16, loop=0)  # every 4th step of 0.08 s: twice real time
        paths.append(path)
    return paths


def evaluate(policy, demo_dir: str | Path, split: str, episodes: int | None = None,
             horizon: int | None = None, videos: int = 0) -> EvalResult:
    """Success rate and average completed sub-tasks of ``policy`` on the ``seen``, ``val`` or ``unseen`` configs
    (recording the first ``videos`` rollouts' frames)."""
    return rollout(policy, load_split_configs(demo_dir, split, episodes), split, horizon or HORIZON, videos=videos)


def evaluate_run(req, info: dict, env_id: str) -> dict:
    """``cotpc eval`` of a kitchen run: ``req`` an :class:`cotpc.evaluation.request.EvalRequest`, ``info`` the
    run's config.json. Writes the per-episode JSON and prints the summary."""
    if req.rules not in (None, "paper"):
        raise SystemExit(f"cotpc eval: {env_id} has no rule variants (--rules {req.rules})")
    demos, weights = req.demos_and_weights(info)
    policy = load_for_eval(weights, req.device, req.inference_overrides(), compile=req.compile)
    result = evaluate(policy, demos, req.split, req.episodes, req.horizon, videos=req.num_videos if req.video else 0)
    if req.video:
        for path in write_videos(result, req.video):
            print(f"wrote {path}")
    result.meta.update({"run": str(req.run), "checkpoint": req.checkpoint, "demos": str(demos),
                        **req.inference_settings()})
    out = req.out or req.run / f"eval_{req.split}{req.variant_suffix()}.json"
    result.to_json(out)
    s = result.summary()
    print(f"{req.run} [{req.split}] success {100 * s['success_rate']:.1f}% (95% CI {100 * s['ci95'][0]:.1f}-"
          f"{100 * s['ci95'][1]:.1f}, n={s['episodes']}), completed sub-tasks {s['mean_completed']:.2f}/4, "
          f"{s['seconds']:.1f} s -> {out}")
    return s


