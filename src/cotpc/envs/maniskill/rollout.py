"""Evaluation on ManiSkill3 tasks: roll a policy out from the seeds of the demos, ManiSkill3's protocol.

- ``seen`` = the seeds of the training demos (``DEMOS/train.json``), ``unseen`` = those of the test demos
  (``DEMOS/test.json``, a disjoint seed range, checked). For PegInsertionSide-v1 ManiSkill3 also draws the peg
  and hole sizes from the seed, so unseen seeds are unseen geometries too.
- Each episode runs the full horizon (the paper's 200 steps for Stack Cube and Peg Insertion, see
  :data:`cotpc.envs.maniskill.env.HORIZONS`) with terminations ignored, and reports ``success_once`` (success at any
  step) and ``success_at_end`` (at the last step), each with a 95% Wilson interval. Progress short of success is
  reported too, like the maze's region transitions: the rate at which each of the task's boolean stage flags
  (e.g. StackCube's ``is_cubeA_grasped``, ``is_cubeA_on_cubeB``) was ever true, and the mean over episodes of
  the highest normalised dense reward reached (ManiSkill3's staged reward, in [0, 1]).
- On CPU: a process pool, each process holding one environment and its own copy of the policy; every episode
  starts from a freshly built scene (``reset(seed, options={"reconfigure": True})``), so its result depends only
  on its seed and the policy, not on the process or the order. With CUDA (``backend="gpu"``): ManiSkill3's
  GPU-parallel simulation (``sim_backend="physx_cuda"``), all episodes of a batch in one scene and one batched
  policy call per step. GPU initial states for a seed differ from the CPU's (ManiSkill3 randomises differently
  on the GPU), so there "seen" means seen seeds, not the demos' exact initial states. The GPU path has not been
  run on our CPU-only machines.
"""

from __future__ import annotations

import functools
import json
import multiprocessing as mp
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch
from tqdm import tqdm

from cotpc.data.trajectories import load_trajectories
from cotpc.envs.maniskill.env import HORIZONS, SEEDS, flat_obs, import_maniskill, key_state_arrays, make_env
from cotpc.evaluation.request import load_for_eval
from cotpc.evaluation.stats import wilson_interval

SPLIT_FILES = {"seen": ("train", "train"), "val": ("val", "val"), "unseen": ("test", "test")}  # split -> (demo file, seed range)
# ManiSkill3's staged dense reward scaled to [0, 1]: its maximum over an episode measures progress short of success.
REWARD_MODE = "normalized_dense"


def load_split_seeds(demo_dir: str | Path, split: str, episodes: int | None = None) -> tuple[str, str, list[int]]:
    """(env_id, control_mode, seeds) of ``seen`` (training demos), ``val`` (validation demos) or ``unseen`` (test
    demos) in ``demo_dir``."""
    if split not in SPLIT_FILES:
        raise ValueError(f"split must be one of {sorted(SPLIT_FILES)}, got {split!r}")
    name, seed_split = SPLIT_FILES[split]
    data = load_trajectories(Path(demo_dir) / f"{name}.h5", extras=())
    env_id = data.env_info.get("env_id")
    if env_id not in HORIZONS:
        raise ValueError(f"{demo_dir}/{name}.json is for {env_id!r}, not a supported ManiSkill3 task {sorted(HORIZONS)}")
    control_mode = data.env_info.get("env_kwargs", {}).get("control_mode") or data.episodes[0].control_mode
    chosen = data.episodes[:episodes] if episodes else data.episodes
    seeds = []
    for ep in chosen:
        seed = int(ep.reset_kwargs["seed"])
        SEEDS.check(seed, seed_split)  # never evaluate "unseen" on a training seed, or the reverse
        seeds.append(seed)
    return env_id, control_mode, seeds


@dataclass
class EvalResult:
    split: str
    env_id: str
    horizon: int
    seeds: list[int]
    success_once: np.ndarray  # (E,) bool
    success_at_end: np.ndarray  # (E,) bool
    first_success: np.ndarray  # (E,) step (1-based) of the first success, -1 if never
    seconds: float
    stages_once: dict[str, np.ndarray] = field(default_factory=dict)  # flag -> (E,) bool: ever true
    max_reward: np.ndarray | None = None  # (E,) highest normalised dense reward of each episode
    meta: dict = field(default_factory=dict)

    def summary(self) -> dict:
        n = len(self.seeds)
        once, end = int(self.success_once.sum()), int(self.success_at_end.sum())
        firsts = self.first_success[self.first_success > 0]
        return {
            "split": self.split,
            "env_id": self.env_id,
            "horizon": self.horizon,
            "episodes": n,
            "success_once": once / max(n, 1),
            "success_once_ci95": list(wilson_interval(once, n)),
            "success_at_end": end / max(n, 1),
            "success_at_end_ci95": list(wilson_interval(end, n)),
            "mean_first_success_step": float(firsts.mean()) if len(firsts) else None,
            "stages_once": {k: float(v.mean()) for k, v in self.stages_once.items()},
            "mean_max_normalized_reward": float(self.max_reward.mean()) if self.max_reward is not None else None,
            "seconds": round(self.seconds, 3),
            **self.meta,
        }

    def to_json(self, path: str | Path) -> None:
        episodes = [
            {"seed": s, "success_once": bool(a), "success_at_end": bool(b), "first_success_step": int(f),
             "stages_once": {k: bool(v[i]) for k, v in self.stages_once.items()},
             "max_normalized_reward": float(self.max_reward[i]) if self.max_reward is not None else None}
            for i, (s, a, b, f) in enumerate(zip(self.seeds, self.success_once, self.success_at_end,
                                                  self.first_success))
        ]
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        Path(path).write_text(json.dumps({"summary": self.summary(), "episodes": episodes}, indent=1))


def _to_numpy(x) -> np.ndarray:
    return x.detach().cpu().numpy() if hasattr(x, "detach") else np.asarray(x)


# ---------------------------------------------------------------- CPU: a pool of processes, one env each

_STATE: dict[str, Any] = {}


def _init_worker(env_id: str, control_mode: str, horizon: int, make_policy: Callable[[], Any], threads: int) -> None:
    torch.set_num_threads(threads)
    _STATE.update(env=make_env(env_id, control_mode, max_episode_steps=horizon, reward_mode=REWARD_MODE),
                  policy=make_policy(), horizon=horizon, env_id=env_id)


def stage_flags(info: dict, env_id: str, env) -> dict[str, np.ndarray]:
    """The task's boolean progress flags in ``info`` (not ``success`` itself), each as a (B,) bool array, and its
    privileged key-state flags (:func:`key_state_arrays`): Peg Insertion's info has none of its own, and progress
    short of success is read from them (peg grasped, pre-inserted)."""
    flags = key_state_arrays(env_id, env, info)
    for key, value in info.items():
        if key in ("success", "fail", "elapsed_steps") or key.startswith("_"):
            continue
        value = _to_numpy(value)
        if value.dtype == bool:
            flags[key] = value.reshape(-1)
    return flags


def _episode(seed: int) -> tuple[int, bool, bool, int, dict[str, bool], float]:
    """One episode from ``seed`` in this process's env: (seed, success_once, success_at_end, first success step,
    stage flags ever true, highest normalised dense reward)."""
    env, policy, horizon, env_id = _STATE["env"], _STATE["policy"], _STATE["horizon"], _STATE["env_id"]
    obs, _ = env.reset(seed=int(seed), options={"reconfigure": True})
    policy.reset()
    first, success, stages, best = -1, False, {}, -np.inf
    for t in range(horizon):
        action = np.asarray(policy.select_action(flat_obs(obs)), dtype=np.float32)[0]
        obs, reward, _, _, info = env.step(action)  # terminations ignored: always the full horizon
        success = bool(_to_numpy(info["success"]).reshape(-1)[0])
        if success and first < 0:
            first = t + 1
        for key, value in stage_flags(info, env_id, env).items():
            stages[key] = stages.get(key, False) or bool(value[0])
        best = max(best, float(_to_numpy(reward).reshape(-1)[0]))
    return int(seed), first > 0, success, first, stages, best


def _collect(results: list[tuple]) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, np.ndarray], np.ndarray]:
    keys = sorted({k for r in results for k in r[4]})
    return (np.array([r[1] for r in results], bool), np.array([r[2] for r in results], bool),
            np.array([r[3] for r in results], int),
            {k: np.array([r[4].get(k, False) for r in results], bool) for k in keys},
            np.array([r[5] for r in results], float))


def rollout_cpu(
    make_policy: Callable[[], Any],
    env_id: str,
    control_mode: str,
    seeds: list[int],
    horizon: int,
    procs: int = 1,
    progress: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, np.ndarray], np.ndarray]:
    """Episodes from ``seeds`` on the CPU simulator; ``make_policy`` (picklable, no arguments) builds the policy
    in each process. Returns success_once, success_at_end, first-success steps, stage flags ever true and the
    highest normalised reward of each episode, in the order of ``seeds``."""
    args = (env_id, control_mode, horizon, make_policy, 1)
    bar = functools.partial(tqdm, total=len(seeds), desc=f"eval {env_id}", unit="ep", disable=not progress,
                            dynamic_ncols=True)
    if procs <= 1:
        _init_worker(*args)
        results = [_episode(s) for s in bar(seeds)]
    else:
        with mp.get_context("spawn").Pool(procs, initializer=_init_worker, initargs=args) as pool:
            results = list(bar(pool.imap(_episode, seeds)))
    return _collect(results)


# ---------------------------------------------------------------- GPU: ManiSkill3's parallel simulation


def rollout_gpu(
    policy,
    env_id: str,
    control_mode: str,
    seeds: list[int],
    horizon: int,
    num_envs: int = 256,
    progress: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, np.ndarray], np.ndarray]:
    """Episodes from ``seeds`` in ManiSkill3's GPU simulation, ``num_envs`` at a time (untested here: no GPU)."""
    n = min(num_envs, len(seeds))
    env = make_env(env_id, control_mode, max_episode_steps=horizon, num_envs=n, sim_backend="physx_cuda",
                   reward_mode=REWARD_MODE)
    results = []
    try:
        for start in tqdm(range(0, len(seeds), n), desc=f"eval {env_id} (gpu)", disable=not progress):
            batch = [int(s) for s in seeds[start:start + n]]
            padded = batch + [batch[-1]] * (n - len(batch))  # the last batch fills the scene with repeats
            obs, _ = env.reset(seed=padded)
            policy.reset()
            first_b = np.full(n, -1)
            success = np.zeros(n, bool)
            stages: dict[str, np.ndarray] = {}
            best = np.full(n, -np.inf)
            for t in range(horizon):
                action = policy.select_action(_to_numpy(obs).astype(np.float32))
                obs, reward, _, _, info = env.step(torch.as_tensor(action, dtype=torch.float32,
                                                                   device=env.unwrapped.device))
                success = _to_numpy(info["success"]).reshape(-1).astype(bool)
                first_b[(first_b < 0) & success] = t + 1
                for key, value in stage_flags(info, env_id, env).items():
                    stages[key] = stages.get(key, np.zeros(n, bool)) | value
                best = np.maximum(best, _to_numpy(reward).reshape(-1))
            for i, seed in enumerate(batch):
                results.append((seed, first_b[i] > 0, success[i], first_b[i], {k: v[i] for k, v in stages.items()},
                                best[i]))
    finally:
        env.close()
    return _collect(results)


# ---------------------------------------------------------------- entry point


def evaluate(
    make_policy: Callable[[], Any],
    demo_dir: str | Path,
    split: str,
    episodes: int | None = None,
    horizon: int | None = None,
    procs: int = 1,
    backend: str = "auto",
    num_envs: int = 256,
    progress: bool = True,
) -> EvalResult:
    """Success rates of the policy built by ``make_policy`` on the ``seen`` or ``unseen`` seeds of ``demo_dir``.

    ``backend``: ``"cpu"`` (process pool of ``procs`` single envs), ``"gpu"`` (ManiSkill3's parallel GPU sim,
    ``num_envs`` at once) or ``"auto"`` (gpu when torch sees CUDA).
    """
    env_id, control_mode, seeds = load_split_seeds(demo_dir, split, episodes)
    horizon = horizon or HORIZONS[env_id]
    if backend == "auto":
        backend = "gpu" if torch.cuda.is_available() else "cpu"
    start = time.perf_counter()
    if backend == "gpu":
        once, end, first, stages, best = rollout_gpu(make_policy(), env_id, control_mode, seeds, horizon, num_envs,
                                                     progress)
    elif backend == "cpu":
        once, end, first, stages, best = rollout_cpu(make_policy, env_id, control_mode, seeds, horizon, procs,
                                                     progress)
    else:
        raise ValueError(f"backend must be 'auto', 'cpu' or 'gpu', got {backend!r}")
    return EvalResult(
        split=split, env_id=env_id, horizon=horizon, seeds=seeds, success_once=once, success_at_end=end,
        first_success=first, seconds=time.perf_counter() - start, stages_once=stages, max_reward=best,
        meta={"control_mode": control_mode, "backend": backend, "procs": procs if backend == "cpu" else None},
    )


def evaluate_run(req, info: dict, env_id: str) -> dict:
    """``cotpc eval`` of a ManiSkill3 run: ``req`` an :class:`cotpc.evaluation.request.EvalRequest`, ``info`` the
    run's config.json. Writes the per-episode JSON and prints the summary."""
    if req.rules not in (None, "paper"):
        raise SystemExit(f"cotpc eval: {env_id} has no rule variants (--rules {req.rules}); {req.run} was trained on it")
    import_maniskill()
    if req.video:
        raise SystemExit("cotpc eval: --video needs a render device for ManiSkill3 tasks; not supported yet")
    demos, weights = req.demos_and_weights(info)
    device = req.device if req.backend != "cpu" else "cpu"
    load = policy_loader(weights, device, req.inference_overrides(), compile=req.compile)
    result = evaluate(load, demos, req.split, req.episodes, horizon=req.horizon, procs=req.procs,
                      backend=req.backend, num_envs=req.num_envs)
    if result.env_id != env_id:
        raise SystemExit(f"cotpc eval: {req.run} was trained on {env_id} but {demos} holds {result.env_id} demos")
    result.meta.update({"run": str(req.run), "checkpoint": req.checkpoint, "demos": str(demos),
                        **req.inference_settings()})
    out = req.out or req.run / f"eval_{req.split}{req.variant_suffix()}.json"
    result.to_json(out)
    s = result.summary()
    lo1, hi1 = s["success_once_ci95"]
    lo2, hi2 = s["success_at_end_ci95"]
    print(
        f"{req.run} [{env_id} {req.split}, horizon {s['horizon']}] success_once {100 * s['success_once']:.1f}% "
        f"(95% CI {100 * lo1:.1f}-{100 * hi1:.1f}), success_at_end {100 * s['success_at_end']:.1f}% "
        f"(95% CI {100 * lo2:.1f}-{100 * hi2:.1f}), n={s['episodes']}, {s['seconds']:.1f} s ({s['backend']}) -> {out}"
    )
    return s


def policy_loader(run_dir: str | Path, device: str = "cpu", overrides: dict | None = None,
                  compile: bool = False) -> Callable[[], Any]:
    """A picklable factory loading ``run_dir`` with :func:`cotpc.load_policy` (one copy per process), with the
    inference settings in ``overrides`` replacing the run's (:func:`cotpc.evaluation.request.load_for_eval`)."""
    return functools.partial(load_for_eval, str(run_dir), device, overrides, compile)


class ReplayPolicy:
    """Plays back a demo's actions (for tests), the demo chosen by its first observation; then holds still."""

    def __init__(self, by_first_obs: list[tuple[np.ndarray, np.ndarray]]):
        self.table = by_first_obs
        self.actions: np.ndarray | None = None
        self.t = 0

    def reset(self) -> None:
        self.actions, self.t = None, 0

    def select_action(self, obs: np.ndarray) -> np.ndarray:
        obs = np.asarray(obs, dtype=np.float32)
        if self.actions is None:
            dists = [np.abs(first - obs[0]).max() for first, _ in self.table]
            self.actions = self.table[int(np.argmin(dists))][1]
        if self.t < len(self.actions):
            a = self.actions[self.t]
        else:  # hold: no arm motion, the gripper as last commanded (its action is absolute)
            a = np.zeros(self.actions.shape[1], np.float32)
            a[-1] = self.actions[-1, -1]
        self.t += 1
        return a[None]


def replay_factory(demo_path: str | Path) -> Callable[[], ReplayPolicy]:
    """A picklable factory of :class:`ReplayPolicy` over the demos in ``demo_path``."""
    return functools.partial(_make_replay, str(demo_path))


def _make_replay(demo_path: str) -> ReplayPolicy:
    data = load_trajectories(demo_path, extras=())
    return ReplayPolicy([(ep.obs[0], ep.actions) for ep in data.episodes])
