"""Why a Stack Cube policy opens the gripper right after closing it: the state one step after each close.

Rolls a trained policy out on validation seeds (never the test seeds) and, one step after each time it tells the
gripper to close, prints the fingers' joint position and velocity (observation dimensions 7 and 16), the
distance (in the policy's normalised units) from that state to the nearest training-demo state, and how many of
the 20 nearest training states were labelled "open". The same quantities for the training demos one step after
their close, and the nearest-neighbour distance of held-out demo states, are printed first for comparison::

    .venv-ms/bin/python scripts/ms-grasp-flip.py RUN --demos runs/dart0.1/StackCube-v1/demos --seeds 1000000,1000002
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from cotpc.data.trajectories import load_trajectories
from cotpc.envs.maniskill.env import flat_obs, make_env
from cotpc.policies import load_policy

FINGER, FINGER_VEL = 7, 16  # Panda: qpos 0-8 (fingers 7, 8), qvel 9-17 (fingers 16, 17)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("run")
    p.add_argument("--demos", type=Path, required=True, help="folder with train.h5 and val.h5")
    p.add_argument("--seeds", default="1000000,1000001,1000002", help="validation seeds, comma-separated")
    p.add_argument("--steps", type=int, default=100)
    args = p.parse_args()
    torch.set_num_threads(1)
    policy = load_policy(args.run)
    obs_mean, obs_std, _, _ = policy._np_stats
    obs_std = np.where(np.isinf(obs_std), 1.0, obs_std)  # dimensions the run hides: compare them raw
    train = load_trajectories(args.demos / "train.h5", extras=())
    states = np.concatenate([ep.obs[:-1] for ep in train.episodes])
    gripper = np.concatenate([ep.actions[:, -1] for ep in train.episodes])
    z_train = (states - obs_mean) / obs_std

    def nearest(o: np.ndarray, k: int = 20) -> tuple[float, int]:
        d = np.linalg.norm(z_train - (o - obs_mean) / obs_std, axis=1)
        idx = np.argsort(d)[:k]
        return float(d[idx[0]]), int((gripper[idx] > 0).sum())

    after = np.array([ep.obs[int(np.argmax(ep.actions[:, -1] < 0)) + 1, [FINGER, FINGER_VEL]] for ep in train.episodes])
    print(f"training demos, one step after the close: fingers median {np.median(after[:, 0]):.4f}, finger velocity "
          f"median {np.median(after[:, 1]):+.3f} (10-90%: {np.percentile(after[:, 1], 10):+.3f} .. "
          f"{np.percentile(after[:, 1], 90):+.3f})")
    val = load_trajectories(args.demos / "val.h5", extras=())
    held_out = [nearest(ep.obs[t])[0] for ep in val.episodes[:10] for t in range(0, len(ep.actions), 7)]
    print(f"held-out demo states: nearest training state at {np.median(held_out):.2f} (median), "
          f"{np.percentile(held_out, 90):.2f} (90%)")
    env = make_env("StackCube-v1", "pd_joint_delta_pos", max_episode_steps=args.steps)
    for seed in (int(s) for s in args.seeds.split(",")):
        obs, _ = env.reset(seed=seed, options={"reconfigure": True})
        policy.reset()
        closed_before = False
        for t in range(args.steps):
            o = flat_obs(obs)[0]
            if closed_before:
                dist, n_open = nearest(o)
                print(f"seed {seed} step {t}, one step after a close: fingers {o[FINGER]:.4f}, finger velocity "
                      f"{o[FINGER_VEL]:+.3f}, nearest training state at {dist:.2f}, {n_open} of its 20 nearest "
                      f"labelled open")
            action = np.asarray(policy.select_action(o[None]), dtype=np.float32)[0]
            closed_before = action[-1] < 0 and o[FINGER] > 0.035  # told to close while open
            obs, *_ = env.step(action)


if __name__ == "__main__":
    main()
