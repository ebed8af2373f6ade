"""Where Stack Cube episodes fail: roll a trained policy out on validation seeds and trace each step.

Per step: cube A grasped / on cube B (ManiSkill3's flags), cube A's height above the table, the horizontal
distance from cube A to cube B, the gripper command and the size of the arm command. Each episode is then put in
the first phase it never got past:

- ``no grasp``: cube A never grasped;
- ``dropped``: grasped, then the grasp was lost before cube A was ever on cube B (with where and how: the gripper
  command at the loss, cube A's height and its distance to B);
- ``not placed``: grasped until the end of the episode without cube A resting on B;
- ``not released``: cube A on B but never released there while static (ManiSkill3's success);
- ``success``.

The same for the demos' own actions, replayed open loop (a check of the tracer: every demo should be a
success). Validation seeds only (never the test seeds)::

    .venv-ms/bin/python scripts/ms-trace.py RUN --demos runs/ms/StackCube-v1/demos --episodes 50 --procs 2 \
        --out RUN/trace_val.json
    .venv-ms/bin/python scripts/ms-trace.py replay --demos runs/ms/StackCube-v1/demos --episodes 20
    .venv-ms/bin/python scripts/ms-trace.py RUN --demos ... --teacher-forced     # gripper decisions on the demos
    .venv-ms/bin/python scripts/ms-trace.py RUN/trace_val.json                   # summarise a saved trace again
    .venv-ms/bin/python scripts/ms-trace.py RUN --demos ... --timestep-shift -15  # how far actions follow time

The summary also has where the gripper was, relative to cube A, when first told to close (median distance,
and the mean part of it short of the cube along the gripper's way from its start, and across that way).
"""

from __future__ import annotations

import argparse
import functools
import json
import multiprocessing as mp
from pathlib import Path

import numpy as np

from cotpc.data.trajectories import load_trajectories
from cotpc.envs.maniskill import rollout
from cotpc.envs.maniskill.env import flat_obs
from cotpc.envs.maniskill.rollout import _make_replay, policy_loader


class ClippedObs:
    """A policy fed observations clipped to [lo, hi] per dimension (an inference-time experiment)."""

    def __init__(self, policy, lo: np.ndarray, hi: np.ndarray):
        self.policy, self.lo, self.hi = policy, lo, hi

    def reset(self) -> None:
        self.policy.reset()

    def select_action(self, obs: np.ndarray) -> np.ndarray:
        return self.policy.select_action(np.clip(obs, self.lo, self.hi).astype(np.float32))


class ShiftedTime:
    """A transformer policy told, from its second step on, that the episode is ``shift`` steps further along
    than it is (an inference-time probe of how much its actions follow the episode timestep)."""

    def __init__(self, policy, shift: int):
        self.policy, self.shift, self.steps = policy, shift, 0

    def reset(self) -> None:
        self.policy.reset()
        self.steps = 0

    def select_action(self, obs: np.ndarray) -> np.ndarray:
        action = self.policy.select_action(obs)
        if self.steps == 0:
            self.policy._t += self.shift  # the timestep of the next observation
        self.steps += 1
        return action


class DebouncedGripper:
    """A policy whose gripper command (the last action dimension, +1 open / -1 closed) changes sign only once the
    policy has asked for the new sign ``steps`` times in a row (an inference-time probe: one-step flips are
    ignored, deliberate ones delayed by ``steps - 1``)."""

    def __init__(self, policy, steps: int):
        self.policy, self.steps = policy, steps
        self.reset()

    def reset(self) -> None:
        self.policy.reset()
        self.command, self.streak = None, 0

    def select_action(self, obs: np.ndarray) -> np.ndarray:
        action = np.array(self.policy.select_action(obs), dtype=np.float32, copy=True)
        wanted = 1.0 if action[0, -1] >= 0 else -1.0
        if self.command is None:
            self.command = wanted
        self.streak = self.streak + 1 if wanted != self.command else 0
        if self.streak >= self.steps:
            self.command, self.streak = wanted, 0
        if np.sign(action[0, -1]) != self.command:
            action[0, -1] = self.command
        return action


def _wrapped_policy(make_policy, clip: tuple | None, shift: int, debounce: int = 1):
    """``make_policy()`` behind the inference-time probes asked for (picklable with functools.partial)."""
    policy = make_policy()
    if debounce > 1:
        policy = DebouncedGripper(policy, debounce)
    if clip is not None:
        policy = ClippedObs(policy, *clip)
    if shift:
        policy = ShiftedTime(policy, shift)
    return policy


def _f(x) -> np.ndarray:
    return np.asarray(x.detach().cpu() if hasattr(x, "detach") else x, dtype=np.float64).reshape(-1)


def trace(seed: int) -> dict:
    env, policy = rollout._STATE["env"], rollout._STATE["policy"]  # built by rollout._init_worker
    obs, _ = env.reset(seed=int(seed), options={"reconfigure": True})
    policy.reset()
    task = env.unwrapped
    start = _f(task.agent.tcp.pose.p)[:2] - _f(task.cubeA.pose.p)[:2]  # from cube A to the gripper, at reset
    rows = []
    for t in range(rollout._STATE["horizon"]):
        action = np.asarray(policy.select_action(flat_obs(obs)), dtype=np.float32)[0]
        before = _f(task.cubeA.pose.p)[:2] - _f(task.agent.tcp.pose.p)[:2]  # the state the action was chosen in
        obs, _, _, _, info = env.step(action)
        a, b, tcp = _f(task.cubeA.pose.p), _f(task.cubeB.pose.p), _f(task.agent.tcp.pose.p)
        rows.append({
            "grasped": bool(_f(info["is_cubeA_grasped"])[0]), "on_b": bool(_f(info["is_cubeA_on_cubeB"])[0]),
            "success": bool(_f(info["success"])[0]), "a_height": float(a[2] - 0.02),
            "xy_to_b": float(np.linalg.norm(a[:2] - b[:2])), "gripper": float(action[-1]),
            "arm": float(np.abs(action[:-1]).max()), "tcp_to_a_xy": float(np.linalg.norm(a[:2] - tcp[:2])),
            "acted_tcp_to_a": [float(before[0]), float(before[1])],
        })
    return {"seed": int(seed), **classify(rows, start), "start_tcp_from_a": start.tolist(), "steps": rows}


def classify(rows: list[dict], start: np.ndarray | None = None) -> dict:
    """The phase an episode never got past, and where its gripper was when first told to close; ``start`` (the
    gripper's horizontal position relative to cube A at reset) splits that offset into ``close_short`` (along
    the way from the start to the cube, > 0: stopped short of it) and ``close_across``."""
    grasped = np.array([r["grasped"] for r in rows])
    on_b = np.array([r["on_b"] for r in rows])
    success = np.array([r["success"] for r in rows])
    closes = [t for t, r in enumerate(rows) if r["gripper"] < 0]
    # the gripper-to-cube offset when the gripper is first told to close (rows[t - 1]: the state it acted in)
    close_offset = rows[closes[0] - 1]["tcp_to_a_xy"] if closes and closes[0] > 0 else None
    short = across = None
    if close_offset is not None and start is not None and "acted_tcp_to_a" in rows[closes[0]]:
        way = -np.asarray(start, dtype=float) / max(np.linalg.norm(start), 1e-9)  # unit vector, gripper -> cube
        off = np.asarray(rows[closes[0]]["acted_tcp_to_a"])  # from the gripper to cube A when it closed
        short, across = float(off @ way), float(off[0] * way[1] - off[1] * way[0])
    runs = np.diff(np.flatnonzero(np.diff(np.r_[0, grasped.astype(int), 0])).reshape(-1, 2), axis=1)
    out = {"first_grasp": int(np.argmax(grasped)) if grasped.any() else None, "close_offset_xy": close_offset,
           "close_step": closes[0] if closes else None, "close_short": short, "close_across": across,
           "longest_grasp": int(runs.max()) if len(runs) else 0,
           "lifted": bool(any(r["grasped"] and r["a_height"] > 0.02 for r in rows)),
           "gripper_switches": int((np.diff(np.sign([r["gripper"] for r in rows])) != 0).sum()),
           "max_height_grasped": float(max((r["a_height"] for r in rows if r["grasped"]), default=0.0)),
           "min_xy_to_b_grasped": float(min((r["xy_to_b"] for r in rows if r["grasped"]), default=np.inf)),
           **_first_release(rows)}
    if success.any():
        return {**out, "phase": "success"}
    if not grasped.any():
        return {**out, "phase": "no grasp"}
    first_on_b = int(np.argmax(on_b)) if on_b.any() else len(rows)
    g = out["first_grasp"]
    losses = [t for t in range(g + 1, first_on_b) if grasped[t - 1] and not grasped[t]]
    if losses:
        t = losses[0]
        before = rows[t - 1]
        return {**out, "phase": "dropped", "loss_step": t, "loss_gripper": rows[t]["gripper"],
                "gripper_before_loss": [r["gripper"] for r in rows[max(0, t - 5):t + 1]],
                "loss_height": before["a_height"], "loss_xy_to_b": before["xy_to_b"],
                "grasped_steps_before_loss": int(t - g), "regrasped": bool(grasped[t:first_on_b].any())}
    if not on_b.any():
        return {**out, "phase": "not placed"}
    return {**out, "phase": "not released", "first_on_b": first_on_b}


def _first_release(rows: list[dict]) -> dict:
    """Where cube A was when the grasp first ended with the cube raised (> 2 cm, so a release over cube B or a drop
    in the air, never a slip at the table): its horizontal distance from cube B's centre and its height, in the
    state the policy released in. A 4 cm cube let go > 2 cm off B's centre overhangs by half and rarely rests."""
    for t in range(1, len(rows)):
        if rows[t - 1]["grasped"] and not rows[t]["grasped"] and rows[t - 1]["a_height"] > 0.02:
            return {"release_xy_to_b": rows[t - 1]["xy_to_b"], "release_height": rows[t - 1]["a_height"]}
    return {"release_xy_to_b": None, "release_height": None}


def _mean_mm(values: list) -> float | None:
    values = [v for v in values if v is not None]
    return round(1000 * float(np.mean(values)), 1) if values else None


def summarise(episodes: list[dict]) -> dict:
    phases = [e["phase"] for e in episodes]
    counts = {p: phases.count(p) for p in ("no grasp", "dropped", "not placed", "not released", "success")}
    drops = [e for e in episodes if e["phase"] == "dropped"]
    offsets = [e["close_offset_xy"] for e in episodes if e["close_offset_xy"] is not None]
    summary = {"episodes": len(episodes), "phases": counts,
               "close_offset_xy_mm": {q: round(1000 * float(np.percentile(offsets, p)), 1)
                                      for q, p in (("p25", 25), ("median", 50), ("p75", 75))} if offsets else None,
               "close_step_median": float(np.median([e["close_step"] for e in episodes if e["close_step"] is not None]
                                                    or [np.nan])),
               "close_short_mm_mean": _mean_mm([e.get("close_short") for e in episodes]),
               "close_across_mm_abs_mean": _mean_mm([abs(e["close_across"]) if e.get("close_across") is not None
                                                     else None for e in episodes]),
               "mean_gripper_switches": float(np.mean([e["gripper_switches"] for e in episodes])),
               # ManiSkill3's is_cubeA_grasped also holds for a step of an off-centre grasp: how many held on
               "grasped_once": float(np.mean([e["first_grasp"] is not None for e in episodes])),
               "held_10_steps": float(np.mean([e["longest_grasp"] >= 10 for e in episodes])),
               "lifted_2cm": float(np.mean([e["lifted"] for e in episodes])),
               "mean_max_height_grasped": float(np.mean([e["max_height_grasped"] for e in episodes
                                                         if e["first_grasp"] is not None] or [np.nan]))}
    released = [e["release_xy_to_b"] for e in episodes if e.get("release_xy_to_b") is not None]
    if released:  # how precisely cube A is put over B (traces made before this was recorded have none)
        summary["release_xy_to_b_mm"] = {
            "released": len(released), "median": round(1000 * float(np.median(released)), 1),
            "p75": round(1000 * float(np.percentile(released, 75)), 1),
            "over_20mm": round(float(np.mean(np.array(released) > 0.02)), 3)}
    if drops:
        summary["dropped"] = {
            "gripper_command_at_loss": [round(e["loss_gripper"], 3) for e in drops],
            "height_at_loss": [round(e["loss_height"], 3) for e in drops],
            "xy_to_b_at_loss": [round(e["loss_xy_to_b"], 3) for e in drops],
            "grasped_steps_before_loss": [e["grasped_steps_before_loss"] for e in drops],
            "regrasped": sum(e["regrasped"] for e in drops),
        }
    return summary


def teacher_forced(run: str, demos: Path, episodes: int) -> dict:
    """The policy's gripper decisions on the validation demos' own states and past actions (no simulation): at
    the step each demo closes the gripper, at the step it opens it, and how many of the steps between (holding)
    or before (approaching) it gets wrong per demo, and where the wrong ones are: within ``near`` steps before
    the close or the release, or in the middle of the hold (more than ``near`` steps from both); and the mean
    absolute error of its arm actions."""
    near = 10
    from cotpc.policies import load_policy

    policy = load_policy(run)
    _, _, act_mean, act_std = policy._np_stats
    close_wrong, release_wrong, hold_open, approach_closed, arm_err = [], [], [], [], []
    wrong_where = {"before_close": 0, "mid_hold": 0, "before_release": 0, "elsewhere": 0}
    for ep in load_trajectories(demos / "val.h5", extras=()).episodes[:episodes]:
        policy.reset()
        predicted = []
        for t, action in enumerate(ep.actions):
            predicted.append(policy.select_action(ep.obs[t:t + 1])[0])
            policy._actions[:, -1] = (action - act_mean) / act_std  # the demo's action, not the policy's
        predicted = np.array(predicted)
        grip, want = np.sign(predicted[:, -1]), np.sign(ep.actions[:, -1])
        close, release = int(np.argmax(want < 0)), int(len(want) - np.argmax(want[::-1] < 0))
        close_wrong.append(grip[close] != -1)
        release_wrong.append(release < len(want) and grip[release] != 1)
        hold_open.append(int((grip[close + 1:release] == 1).sum()))
        approach_closed.append(int((grip[:close] == -1).sum()))
        arm_err.append(float(np.abs(predicted[:, :-1] - ep.actions[:, :-1]).mean()))
        for t in np.flatnonzero(grip != want):
            where = ("before_close" if close - near <= t <= close else
                     "before_release" if release - near <= t <= release else
                     "mid_hold" if close < t < release - near else "elsewhere")
            wrong_where[where] += 1
    return {"episodes": len(close_wrong), "close_step_wrong": float(np.mean(close_wrong)),
            "release_step_wrong": float(np.mean(release_wrong)),
            "holding_steps_predicted_open_per_demo": float(np.mean(hold_open)),
            "approach_steps_predicted_closed_per_demo": float(np.mean(approach_closed)),
            "arm_abs_error": float(np.mean(arm_err)),
            f"wrong_gripper_steps_where (near = {near} steps)": wrong_where}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("run", help="a run directory, 'replay' for the validation demos' own actions, or a trace "
                               "written by --out (its episodes are summarised again, nothing is run)")
    p.add_argument("--demos", type=Path, help="the demo folder (its val.h5 seeds; train.h5 for --clip-obs)")
    p.add_argument("--episodes", type=int, default=50)
    p.add_argument("--horizon", type=int, default=200)
    p.add_argument("--procs", type=int, default=1)
    p.add_argument("--out", type=Path)
    p.add_argument("--action-rule", choices=("mode", "mean", "sample"), help="as cotpc eval --action-rule")
    p.add_argument("--timestep-shift", type=int, default=0,
                   help="tell a transformer policy the episode is this many steps further along than it is")
    p.add_argument("--teacher-forced", action="store_true",
                   help="no rollouts: the gripper decisions on the validation demos' own states and actions")
    p.add_argument("--clip-obs", default="none",
                   help="none; 'range' (each dimension clipped to the training demos' min-max); or a number z "
                        "(clipped to mean +- z std of the training demos)")
    p.add_argument("--zero-obs", default="",
                   help="comma-separated observation dimensions the policy is shown as 0 (e.g. 16,17: Stack Cube's "
                        "finger joint velocities)")
    p.add_argument("--gripper-debounce", type=int, default=1,
                   help="switch the gripper command only after this many steps asking for it in a row (1 = off)")
    args = p.parse_args()
    if args.run.endswith(".json"):
        episodes = json.loads(Path(args.run).read_text())["episodes"]
        for e in episodes:  # traces written before the release was recorded
            e.update({k: v for k, v in _first_release(e["steps"]).items() if e.get(k) is None})
        print(json.dumps(summarise(episodes), indent=1))
        return
    if args.demos is None:
        raise SystemExit("ms-trace: --demos is needed to run rollouts")
    if args.run != "replay" and not (Path(args.run) / "config.json").exists():
        raise SystemExit(f"ms-trace: {args.run} is not a run directory (no config.json)")  # before any pool starts
    if args.teacher_forced:
        summary = teacher_forced(args.run, args.demos, args.episodes)
        print(json.dumps(summary, indent=1))
        if args.out:
            args.out.write_text(json.dumps({"summary": summary}))
        return
    data = load_trajectories(args.demos / "val.h5", extras=())
    seeds = [int(ep.reset_kwargs["seed"]) for ep in data.episodes[:args.episodes]]
    if args.run == "replay":
        make_policy = functools.partial(_make_replay, str(args.demos / "val.h5"))
    else:
        make_policy = policy_loader(args.run, overrides={"action_rule": args.action_rule} if args.action_rule else None)
    clip = None
    if args.clip_obs != "none":
        train = np.concatenate([ep.obs for ep in load_trajectories(args.demos / "train.h5", extras=()).episodes])
        if args.clip_obs == "range":
            clip = (train.min(0), train.max(0))
        else:
            z = float(args.clip_obs)
            clip = (train.mean(0) - z * train.std(0), train.mean(0) + z * train.std(0))
    if args.zero_obs:
        dims = [int(d) for d in args.zero_obs.split(",")]
        obs_dim = data.episodes[0].obs.shape[1]
        lo, hi = np.full(obs_dim, -np.inf, np.float32), np.full(obs_dim, np.inf, np.float32)
        if clip is not None:
            lo, hi = np.asarray(clip[0], np.float32).copy(), np.asarray(clip[1], np.float32).copy()
        lo[dims] = hi[dims] = 0.0
        clip = (lo, hi)
    make_probed = functools.partial(_wrapped_policy, make_policy, clip, args.timestep_shift,
                                    args.gripper_debounce)
    with mp.get_context("spawn").Pool(args.procs, initializer=rollout._init_worker,
                                      initargs=("StackCube-v1", "pd_joint_delta_pos", args.horizon, make_probed, 1)) as pool:
        episodes = pool.map(trace, seeds)
    summary = summarise(episodes)
    print(json.dumps(summary, indent=1))
    if args.out:
        args.out.write_text(json.dumps({"summary": summary, "episodes": episodes}))


if __name__ == "__main__":
    main()
