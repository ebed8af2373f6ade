"""ManiSkill3 demonstrations from the official motion planners, converted to state observations.

For each seed of a split (in order, from :data:`cotpc.envs.maniskill.env.SEEDS`):

1. ManiSkill3's motion-planning solution for the task (``mani_skill.examples.motionplanning.panda``) drives an
   environment in ``pd_joint_pos`` (what the planners output), headless; a seed whose plan fails or does not end
   in success is skipped (recorded in the JSON as failed).
2. The ``pd_joint_pos`` actions are converted to ``pd_joint_delta_pos`` (or ``pd_ee_delta_pose``) by ManiSkill's
   own converter (``mani_skill.trajectory.utils.actions.conversion.from_pd_joint_pos``, what
   ``python -m mani_skill.trajectory.replay_trajectory -c ...`` runs), stepping an environment with state
   observations from the same ``reset(seed)``; its observations, actions and per-step success are recorded.
   Only conversions that end in success are kept.

The demo set of a split is therefore the first ``num`` seeds of its range (from ``offset``) that both steps
solve: the same for any ``--procs`` and after any interruption. Progress is saved every few demos in
``OUT/<split>-partial.{h5,json}`` and a re-run continues from there (or extends a finished ``OUT/<split>.h5``).
"""

from __future__ import annotations

import collections
import contextlib
import io
import multiprocessing as mp
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, Optional

import gymnasium as gym
import numpy as np
import torch
from tqdm import tqdm

from cotpc.data.trajectories import Episode, TrajectoryFormatError, TrajectorySet, load_trajectories, save_trajectories
from cotpc.envs.spec import check_demo_flags
from cotpc.envs.maniskill.env import (
    CONTROL_MODES, HORIZONS, KEY_STATE_FLAGS, SEEDS, flat_obs, import_maniskill, key_state_flags, key_steps_from_flags,
    make_env,
)

PLAN_CONTROL_MODE = "pd_joint_pos"
PLAN_STEP_LIMIT = 1000  # no time limit interferes with planning or conversion (planner demos are ~100-300 steps)


def shorten_close_holds(plan_actions: np.ndarray, keep: int) -> np.ndarray:
    """The planner's actions with each hold after a gripper close cut to its first ``keep`` steps.

    ManiSkill3's planner closes the gripper by repeating one action (arm target fixed, gripper closed) for 6
    steps; the fingers reach the object in ~2 of them, so the rest is a pause in which the state no longer
    changes and only a step counter says when the lift starts. Cut short, the arm moves on as soon as the
    fingers have closed: a pause the state shows. The actions are re-executed (converted) afterwards, so the
    demos stay physically consistent, and only those that still succeed are kept."""
    if keep < 1:
        raise ValueError(f"keep must be >= 1, got {keep}")
    gripper = plan_actions[:, -1]
    drop = np.zeros(len(plan_actions), dtype=bool)
    for start in np.flatnonzero(np.diff(gripper) < 0) + 1:  # the first step of each close
        end = start + 1
        while end < len(plan_actions) and np.array_equal(plan_actions[end], plan_actions[start]):
            end += 1
        drop[start + keep:end] = True
    return plan_actions[~drop]


def planner_solutions() -> dict:
    """ManiSkill3's motion-planning solutions, by env id."""
    from mani_skill.examples.motionplanning.panda.run import MP_SOLUTIONS  # the optional [maniskill] extra

    return MP_SOLUTIONS


@dataclass(frozen=True)
class Demonstrator:
    """How the planner's training demos are altered (all off: the planner's own demos, as the paper's).

    ``action_noise``: DART-style noise on the executed arm actions (Laskey et al., 2017), Gaussian of this std in
    normalised action units, the clean (corrective) actions recorded; ``grasped_noise``: that std instead while the
    object is held (None = ``action_noise`` throughout); ``close_hold``: steps the arm holds still after each
    gripper close (None = the planner's own 6, :func:`shorten_close_holds`); ``hold_after_success``: steps of
    holding still (zero arm deltas, the gripper as last commanded, no noise) appended after the plan's success,
    :meth:`Recorder.hold_still`."""

    action_noise: float = 0.0
    grasped_noise: float | None = None
    close_hold: int | None = None
    hold_after_success: int = 0

    def __post_init__(self):
        for name in ("action_noise", "grasped_noise"):
            std = getattr(self, name)
            if std is not None and not (np.isfinite(std) and std >= 0):
                raise ValueError(f"--{name.replace('_', '-')} must be a std >= 0, got {std}")
        if self.close_hold is not None and self.close_hold < 1:
            raise ValueError(f"--close-hold must be >= 1 step, got {self.close_hold}")
        if self.hold_after_success < 0:
            raise ValueError(f"--hold-after-success must be >= 0 steps, got {self.hold_after_success}")

    def noise_std(self, grasped_now: bool) -> float:
        return self.grasped_noise if self.grasped_noise is not None and grasped_now else self.action_noise

    def generation_key(self) -> dict:
        """The entries a demo file's generation key holds: none for the planner's own demos, so files made before
        an option existed resume as before; a ``grasped_noise`` of 0 is a setting, not "off"."""
        key = {"action_noise": self.action_noise} if self.action_noise else {}
        key |= {"grasped_noise": self.grasped_noise} if self.grasped_noise is not None else {}
        key |= {"close_hold": self.close_hold} if self.close_hold is not None else {}
        return key | ({"hold_after_success": self.hold_after_success} if self.hold_after_success else {})

    @staticmethod
    def describe(gen: dict) -> str:
        """How a file's demos were altered (from its generation key), for its source description; "" if not."""
        text = ""
        grasped = gen.get("grasped_noise")
        if gen.get("action_noise") or grasped is not None:
            while_grasped = f", {grasped} while the object is grasped" if grasped is not None else ""
            text += (f"; arm actions executed with Gaussian noise of std {gen.get('action_noise', 0.0)} (normalised)"
                     f"{while_grasped}, the clean (corrective) actions recorded")
        if gen.get("close_hold") is not None:
            text += f"; the arm held still {gen['close_hold']} steps after each gripper close (the planner's own: 6)"
        if gen.get("hold_after_success"):
            text += f"; {gen['hold_after_success']} steps of holding still (zero arm deltas) appended after the success"
        return text


class Recorder(gym.Wrapper):
    """Records the actions passed to step(), the flat observations, info['success'] and (with ``key_flags_of``,
    an env id) the task's privileged key-state flags since reset().

    With a ``demonstrator``'s noise (:class:`Demonstrator`) the arm part of each action (all but the last, the
    gripper's, dimension) is executed with Gaussian noise added (in normalised units, clipped to [-1, 1]) while the clean action is
    recorded, from a generator seeded by the episode's seed: DART-style demos (Laskey et al., 2017). The
    converter computes each joint-delta action from the *current* joint positions to the planner's next target,
    so the recorded action after a noisy step is the correction back to the plan. ``grasped_noise`` (needs
    ``key_flags_of``) applies while the task's first key-state flag (the object grasped) held after the previous
    step: larger corrections where the object is carried, the grasp untouched."""

    def __init__(self, env, record_obs: bool, key_flags_of: str | None = None,
                 demonstrator: Demonstrator = Demonstrator()):
        super().__init__(env)
        if demonstrator.grasped_noise is not None and not KEY_STATE_FLAGS.get(key_flags_of or ""):
            raise ValueError("noise while grasped needs key_flags_of, a task with key-state flags: the grasp is "
                             "read from the first of them")
        self.record_obs, self.key_flags_of, self.demonstrator = record_obs, key_flags_of, demonstrator
        self.rng = np.random.default_rng(0)

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        self.obs, self.actions, self.success = [flat_obs(obs)[0]] if self.record_obs else [], [], []
        self.key_flags = []
        if kwargs.get("seed") is not None:
            self.rng = np.random.default_rng(int(kwargs["seed"]))
        return obs, info

    def _with_noise(self, action, std: float):
        noise = self.rng.normal(0.0, std, size=np.shape(action)[-1] - 1)
        if hasattr(action, "detach"):
            noisy = action.clone()
            noisy[..., :-1] = (noisy[..., :-1] + torch.as_tensor(noise, dtype=noisy.dtype, device=noisy.device)).clamp(-1, 1)
            return noisy
        noisy = np.array(action, dtype=np.float32, copy=True)
        noisy[..., :-1] = np.clip(noisy[..., :-1] + noise, -1, 1)
        return noisy

    def step(self, action):
        std = self.demonstrator.noise_std(grasped_now=bool(self.key_flags and self.key_flags[-1][0]))
        executed = self._with_noise(action, std) if std > 0 else action
        obs, reward, terminated, truncated, info = self.env.step(executed)
        a = action.detach().cpu().numpy() if hasattr(action, "detach") else np.asarray(action)
        self.actions.append(np.asarray(a, dtype=np.float32).reshape(-1))
        if self.record_obs:
            self.obs.append(flat_obs(obs)[0])
        self.success.append(bool(np.asarray(_cpu(info["success"])).reshape(-1)[0]))
        if self.key_flags_of:
            self.key_flags.append(list(key_state_flags(self.key_flags_of, self.env, info).values()))
        return obs, reward, terminated, truncated, info

    def hold_still(self, steps: int) -> None:
        """Step ``steps`` times with zero arm deltas and the gripper as last commanded, executed without noise:
        in the delta control modes (every mode demos are converted to) that is the action that keeps the arm
        where it is, so a demo goes on showing what to do once the task is done (nothing), where the planner's
        demo ends at once and policies run off their data (docs/results/maniskill.md, success_at_end)."""
        if not self.actions:
            raise ValueError("hold_still needs a recorded action (the gripper's command to keep)")
        hold = np.zeros_like(self.actions[-1])
        hold[-1] = self.actions[-1][-1]
        demonstrator, self.demonstrator = self.demonstrator, Demonstrator()
        try:
            for _ in range(steps):
                self.step(hold)
        finally:
            self.demonstrator = demonstrator


class _Worker:
    """One process's environments (built once): planner env, original-mode env and target env for conversion."""

    def __init__(self, env_id: str, control_mode: str, demonstrator: Demonstrator = Demonstrator()):
        solutions = planner_solutions()
        if env_id not in solutions:
            raise ValueError(f"ManiSkill3 has no motion-planning solution for {env_id}; choose from {sorted(solutions)}")
        self.env_id, self.control_mode, self.demonstrator = env_id, control_mode, demonstrator
        self.solve = solutions[env_id]
        self.plan_env = Recorder(make_env(env_id, PLAN_CONTROL_MODE, obs_mode="none", max_episode_steps=PLAN_STEP_LIMIT), False)
        self.ori_env = make_env(env_id, PLAN_CONTROL_MODE, obs_mode="none", max_episode_steps=PLAN_STEP_LIMIT)
        self.env = Recorder(make_env(env_id, control_mode, obs_mode="state", max_episode_steps=PLAN_STEP_LIMIT), True,
                            key_flags_of=env_id, demonstrator=demonstrator)

    def run(self, seed: int) -> dict[str, Any]:
        """Plan and convert one seed: a dict with ``ok`` and, when ok, obs/actions/success and timings."""
        from mani_skill.trajectory.utils.actions import conversion  # the optional [maniskill] extra

        seed = int(seed)
        t0 = time.perf_counter()
        # Rebuild each scene first: PhysX (CPU) results in contact-rich steps depend on the scene's history, so
        # without this a demo would depend on which seeds the same process ran before it (measured: actions
        # differ by up to 3e-3). With it every demo is a pure function of its seed, for any --procs.
        for env in (self.plan_env, self.ori_env, self.env):
            env.reset(seed=seed, options={"reconfigure": True})
        try:
            with contextlib.redirect_stdout(io.StringIO()):  # the planners print on failure
                res = self.solve(self.plan_env, seed=seed, debug=False, vis=False)
        except Exception as e:  # noqa: BLE001 - planner errors are a failed seed, like ManiSkill's run.py
            return {"seed": seed, "ok": False, "reason": f"planner error: {e}"}
        plan_ok = res != -1 and bool(self.plan_env.success and self.plan_env.success[-1])
        t1 = time.perf_counter()
        if not plan_ok:
            return {"seed": seed, "ok": False, "reason": "planner failed", "plan_s": t1 - t0}
        plan_actions = np.stack(self.plan_env.actions)
        if self.demonstrator.close_hold is not None:
            plan_actions = shorten_close_holds(plan_actions, self.demonstrator.close_hold)
        self.ori_env.reset(seed=seed)
        self.env.reset(seed=seed)
        try:
            conversion.from_pd_joint_pos(self.control_mode, plan_actions, self.ori_env, self.env)
        except Exception as e:  # noqa: BLE001
            return {"seed": seed, "ok": False, "reason": f"conversion error: {e}", "plan_s": t1 - t0}
        t2 = time.perf_counter()
        if not self.env.success or not self.env.success[-1]:
            return {"seed": seed, "ok": False, "reason": "converted actions fail", "plan_s": t1 - t0}
        if self.demonstrator.hold_after_success:
            self.env.hold_still(self.demonstrator.hold_after_success)
            if not self.env.success[-1]:
                return {"seed": seed, "ok": False, "reason": "success lost while holding still", "plan_s": t1 - t0}
        n_flags = len(KEY_STATE_FLAGS.get(self.env_id, ()))
        key_flags = np.array(self.env.key_flags, dtype=bool).reshape(len(self.env.actions), n_flags)
        return {
            "seed": seed,
            "ok": True,
            "obs": np.stack(self.env.obs).astype(np.float32),
            "actions": np.stack(self.env.actions).astype(np.float32),
            "success": np.array(self.env.success, dtype=bool),
            "key_flags": key_flags,
            "key_steps": key_steps_from_flags(self.env_id, key_flags) if n_flags else None,
            "plan_steps": len(plan_actions),
            "plan_s": t1 - t0,
            "convert_s": t2 - t1,
        }


def _key_state_extras(env_id: str, r: dict) -> dict:
    """The privileged key-state flags (per step) and key steps of a demo, as Episode extras (none for a task
    without :data:`KEY_STATE_FLAGS`)."""
    names = KEY_STATE_FLAGS.get(env_id)
    if not names:
        return {}
    return {
        "extras": {"key_flags": r["key_flags"], "key_steps": r["key_steps"]},
        "extra_attrs": {
            "key_flags": {"names": list(names), "description": "privileged key-state flags per step (of the state "
                          "after each action), as the official CoTPC code's patched environments report them"},
            "key_steps": {"description": "privileged key states (state indices) by the official CoTPC code's "
                          "rules (cotpc.envs.maniskill.env.key_steps_from_flags); the final state is implied"},
        },
    }


def _cpu(x):
    return x.detach().cpu().numpy() if hasattr(x, "detach") else x


_WORKER: _Worker | None = None


def _init_worker(env_id: str, control_mode: str, threads: int = 1, demonstrator: Demonstrator = Demonstrator()) -> None:
    global _WORKER
    torch.set_num_threads(threads)
    _WORKER = _Worker(env_id, control_mode, demonstrator)


def _run_seed(seed: int) -> dict[str, Any]:
    assert _WORKER is not None
    return _WORKER.run(seed)


def _generation_key(env_id: str, control_mode: str, split: str, offset: int,
                    demonstrator: Demonstrator = Demonstrator()) -> dict:
    """What a demo file was generated with (a resumed file must match); options left at their defaults are
    absent, so files made before an option existed resume as before."""
    return {"env_id": env_id, "control_mode": control_mode, "split": split, "offset": offset,
            **demonstrator.generation_key()}


def _load_progress(paths: list[Path], key: dict) -> tuple[list[Episode], dict] | None:
    """The saved progress with the most demos among ``paths`` made with the same generation key, if any."""
    best = None
    for path in paths:
        if not path.with_suffix(".h5").exists():
            continue
        try:
            data = load_trajectories(path)  # with the extras (key-state flags and steps): they are saved again
        except TrajectoryFormatError:
            continue
        gen = data.meta.get("cotpc_generation", {})
        if {k: gen.get(k) for k in key} != key:
            raise SystemExit(
                f"{path}.h5 was generated with {({k: gen.get(k) for k in key})}, not {key}; "
                "choose another --out or remove it"
            )
        if best is None or len(data) > len(best[0]):
            best = (data.episodes, gen)
    return best


def _trajectory_set(episodes: list[Episode], env_id: str, control_mode: str, gen: dict) -> TrajectorySet:
    env_info = {
        "env_id": env_id,
        "env_kwargs": {"obs_mode": "state", "control_mode": control_mode, "sim_backend": "physx_cpu",
                       "render_mode": None},
        "max_episode_steps": HORIZONS.get(env_id),
    }
    meta = {
        "source_type": "motionplanning",
        "source_desc": "ManiSkill3 official motion-planning solution (pd_joint_pos), converted with ManiSkill's "
        f"action conversion to {control_mode}; state observations (cotpc demos maniskill)"
        + Demonstrator.describe(gen),
        "cotpc_generation": gen,
    }
    return TrajectorySet(episodes=episodes, env_info=env_info, meta=meta)


def generate_split(
    env_id: str,
    split: str,
    num: int,
    out: str | Path,
    control_mode: str = "pd_joint_delta_pos",
    procs: int = 1,
    offset: int = 0,
    max_attempts: int | None = None,
    save_every: int = 25,
    progress: bool = True,
    demonstrator: Demonstrator = Demonstrator(),
) -> Path:
    """Generate ``num`` successful demos of ``split`` into ``OUT/<split>.{h5,json}`` (resuming saved progress)."""
    if control_mode not in CONTROL_MODES:
        raise ValueError(f"control mode must be one of {CONTROL_MODES}, got {control_mode!r}")
    out = Path(out)
    final, partial = out / split, out / f"{split}-partial"
    key = _generation_key(env_id, control_mode, split, offset, demonstrator)
    lo, hi = SEEDS.range(split)
    found = _load_progress([final, partial], key)
    episodes, failed, next_seed, stats = [], [], lo + offset, {"plan_s": 0.0, "convert_s": 0.0}
    if found:
        episodes, gen = found
        failed, next_seed = list(gen.get("failed_seeds", [])), int(gen["next_seed"])
        stats = dict(gen.get("seconds", stats))
    if found and found[1].get("complete") and len(episodes) == num:
        print(f"{split}: {final}.h5 already holds {num} demos of {env_id} ({control_mode}); nothing to do")
        return final.with_suffix(".h5")
    if len(episodes) > num:  # asked for fewer than were made: keep the first num (the same as a fresh run's)
        episodes = episodes[:num]
        next_seed = int(episodes[-1].reset_kwargs["seed"]) + 1
        failed = [s for s in failed if s < next_seed]
    max_attempts = max_attempts if max_attempts is not None else 3 * num + 50
    start = time.perf_counter()
    last_save = [time.perf_counter(), len(episodes)]

    def gen_info(done: bool) -> dict:
        return {**key, "seed_range": [lo, hi], "next_seed": next_seed, "failed_seeds": failed,
                "attempted": next_seed - lo - offset, "kept": len(episodes), "complete": done,
                "seconds": {k: round(v, 2) for k, v in stats.items()}}

    def save(path: Path, done: bool) -> None:
        if episodes:
            save_trajectories(path, _trajectory_set(episodes, env_id, control_mode, gen_info(done)))
        last_save[:] = [time.perf_counter(), len(episodes)]

    def accept(r: dict) -> None:
        nonlocal next_seed
        SEEDS.check(r["seed"], split)
        next_seed = r["seed"] + 1
        stats["plan_s"] += r.get("plan_s", 0.0)
        stats["convert_s"] += r.get("convert_s", 0.0)
        if r["ok"]:
            episodes.append(Episode(
                obs=r["obs"], actions=r["actions"], success=r["success"], episode_id=len(episodes),
                reset_kwargs={"seed": r["seed"]}, control_mode=control_mode, **_key_state_extras(env_id, r),
            ))
        else:
            failed.append(r["seed"])
        if len(episodes) - last_save[1] >= save_every or (time.perf_counter() - last_save[0] > 60 and episodes):
            save(partial, False)

    bar = tqdm(total=num, initial=len(episodes), desc=f"{env_id} {split}", unit="demo", disable=not progress,
               dynamic_ncols=True)
    pool = None
    try:
        if procs <= 1:
            _init_worker(env_id, control_mode, threads=1, demonstrator=demonstrator)
        else:
            pool = mp.get_context("spawn").Pool(procs, initializer=_init_worker,
                                               initargs=(env_id, control_mode, 1, demonstrator))
        pending: collections.deque = collections.deque()
        seed_iter = iter(range(next_seed, hi))
        while len(episodes) < num:
            attempted = next_seed - lo - offset
            if attempted >= max_attempts and not pending:
                raise RuntimeError(
                    f"{env_id} {split}: only {len(episodes)} of {num} demos after {attempted} seeds "
                    f"(planner success too low); raise --max-attempts"
                )
            if pool is None:
                r = _run_seed(next(seed_iter))
            else:  # keep 2 seeds per process in flight; take results in seed order
                while len(pending) < 2 * procs and attempted + len(pending) < max_attempts:
                    pending.append(pool.apply_async(_run_seed, (next(seed_iter),)))
                r = pending.popleft().get()
            n_before = len(episodes)
            accept(r)
            bar.update(len(episodes) - n_before)
            tried = next_seed - lo - offset
            bar.set_postfix(planner_ok=f"{len(episodes) / max(tried, 1):.0%}", seed=str(next_seed - 1))
        if pool is not None:
            pool.terminate()  # drop seeds planned ahead but not needed
            pool = None
    except KeyboardInterrupt:
        save(partial, False)
        raise SystemExit(f"interrupted: {len(episodes)} demos saved in {partial}.h5; re-run the same command to resume")
    finally:
        bar.close()
        if pool is not None:
            pool.terminate()
    save(final, True)
    for suffix in (".h5", ".json"):
        partial.with_suffix(suffix).unlink(missing_ok=True)
    lengths = np.array([ep.num_steps for ep in episodes])
    tried = next_seed - lo - offset
    print(
        f"{split}: {len(episodes)} demos of {env_id} ({control_mode}) -> {final}.h5 in {time.perf_counter() - start:.1f} s; "
        f"{tried} seeds tried ({len(failed)} failed), steps mean {lengths.mean():.1f} min {lengths.min()} max {lengths.max()}"
    )
    return final.with_suffix(".h5")


def write_splits(env_id: str, out: Path, num: int, test: int, control_mode: str = "pd_joint_delta_pos",
                 procs: int = 1, offset: int = 0, max_attempts: int | None = None,
                 progress: bool = True, val: int = 0, demonstrator: Demonstrator = Demonstrator()) -> dict[str, Path]:
    """``num`` training, ``val`` validation and ``test`` test demos of ``env_id`` (:func:`generate_split`),
    written to ``out/{train,val,test}.{h5,json}``; resumes or extends what is there. Returns the paths.

    ``demonstrator`` alters the training demos only: the validation and test splits are the planner's own, so
    their seeds (the evaluation sets: a seed whose demo fails is skipped) are the same for any demonstrator."""
    import_maniskill()
    start = time.perf_counter()
    paths = {}
    for split, n in (("train", num), ("val", val), ("test", test)):
        if n > 0:
            paths[split] = generate_split(env_id, split, n, out, control_mode=control_mode, procs=procs,
                                          offset=offset, max_attempts=max_attempts, progress=progress,
                                          demonstrator=demonstrator if split == "train" else Demonstrator())
    print(f"generated in {time.perf_counter() - start:.1f} s")
    return paths


@dataclass
class ManiSkillDemos:
    """ManiSkill3 demos (needs `pip install -e '.[maniskill]'`): the official motion planner runs headless, its
    pd_joint_pos actions are converted by ManiSkill's converter to --control-mode with state observations, and
    only demos that succeed after conversion are kept. Writes OUT/train.{h5,json} (seeds 0.., the 'seen' seeds),
    OUT/val.{h5,json} (seeds 1000000.., for choosing settings and checkpoints) and OUT/test.{h5,json}
    (seeds 2000000.., the 'unseen' seeds). Saves progress every few demos; re-running the
    same command resumes (or extends a finished split to a larger --num)."""

    env: str = "StackCube-v1"
    """ManiSkill3 task with a motion-planning solution: StackCube-v1, PegInsertionSide-v1, PickCube-v1,
    PushCube-v1, ... (the paper used 500 Stack Cube and 1000 Peg Insertion demos)."""
    out: Path = Path("data/maniskill")
    """Output directory."""
    num: int = 500
    """Number of (successful) training demos."""
    val: int = 0
    """Number of validation demos, from the disjoint validation seed range: choose schedules, settings and
    checkpoints on these seeds, never on the test seeds. Always the planner's own (the options below alter the
    training demos only), so the evaluation seeds do not depend on them."""
    test: int = 100
    """Number of test demos, from the disjoint test seed range (their seeds are the 'unseen' evaluation set)."""
    control_mode: Literal["pd_joint_delta_pos", "pd_ee_delta_pose"] = "pd_joint_delta_pos"
    """Action space of the converted demos."""
    procs: int = 1
    """Processes planning and converting in parallel (the demos are identical for any number)."""
    offset: int = 0
    """Start this far into each split's seed range."""
    max_attempts: Optional[int] = None
    """Give up on a split after this many seeds (default 3 * N + 50)."""
    progress: bool = True
    """Show progress bars."""
    action_noise: float = 0.0
    """Execute the arm actions with Gaussian noise of this std (normalised action units; 0 = off) and record the
    clean actions, DART-style (Laskey et al., 2017): each joint-delta action is computed from the current joint
    positions to the plan's next target, so the demos show corrections back to the plan, which planner demos
    otherwise never do (docs/results/maniskill.md, "Where Stack Cube episodes fail"). Not the paper's demos."""
    grasped_noise: Optional[float] = None
    """The std in place of --action-noise while the object is grasped (the task's first privileged key-state
    flag held after the previous step; tasks with key-state flags only): corrections where the object is carried
    and placed, while the grasp keeps --action-noise (0.2 everywhere spoils the grasp). Default: off."""
    close_hold: Optional[int] = None
    """Steps the arm holds still after the gripper is told to close (default: the planner's own, 6). The fingers
    close in ~2 steps; the rest is a pause the state does not show, which policies fail to time
    (docs/results/maniskill.md). With 2 the arm lifts as soon as the fingers have closed. Not the paper's demos."""
    hold_after_success: int = 0
    """Steps appended to each training demo after its success, the arm held still (zero joint deltas, the gripper
    as last commanded, no noise); a demo that loses its success meanwhile is dropped. The planner's demos end at
    the success, so nothing shows a policy what to do afterwards and it wanders off (success_at_end below
    success_once, docs/results/maniskill.md). 0 = off. Not the paper's demos."""


def make_demos(cfg: ManiSkillDemos) -> dict[str, Path]:
    """``cotpc demos maniskill`` (mani_skill is imported only when demos are made: an optional extra)."""
    check_demo_flags("cotpc demos maniskill", {"--num": cfg.num, "--val": cfg.val, "--test": cfg.test},
                     {"--procs": cfg.procs, "--max-attempts": cfg.max_attempts}, {"--offset": cfg.offset})
    demonstrator = checked_demonstrator("cotpc demos maniskill", cfg.action_noise, cfg.grasped_noise, cfg.close_hold,
                                        env_id=cfg.env, hold_after_success=cfg.hold_after_success)
    return write_splits(cfg.env, cfg.out, cfg.num, cfg.test, control_mode=cfg.control_mode, procs=cfg.procs,
                        offset=cfg.offset, max_attempts=cfg.max_attempts, progress=cfg.progress, val=cfg.val,
                        demonstrator=demonstrator)


def checked_demonstrator(command: str, action_noise: float = 0.0, grasped_noise: float | None = None,
                         close_hold: int | None = None, env_id: str | None = None,
                         hold_after_success: int = 0) -> Demonstrator:
    """The :class:`Demonstrator` of a command's flags (for ``env_id``), or a clear error naming the flag."""
    try:
        demonstrator = Demonstrator(action_noise, grasped_noise, close_hold, hold_after_success)
    except ValueError as e:
        raise SystemExit(f"{command}: {e}") from None
    if grasped_noise is not None and not KEY_STATE_FLAGS.get(env_id):
        raise SystemExit(f"{command}: --grasped-noise reads the grasp from key-state flags, which {env_id} does not "
                         f"have; tasks with them: {sorted(KEY_STATE_FLAGS)}")
    return demonstrator
