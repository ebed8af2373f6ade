"""The Moving Maze demonstrator and the `cotpc demos maze` command."""

import json

import gymnasium as gym
import numpy as np
import pytest

import cotpc.envs  # noqa: F401
from cotpc.cli.main import main as cotpc_main
from cotpc.data import load_trajectories
from cotpc.envs.maze.demos import MAX_LEG_STEPS, STEP_MAGNITUDE, _StaticMaze, plan_demo
from cotpc.envs.maze.env import HORIZON, MOVING_RANGES, region_of, split_of_seed


@pytest.fixture(scope="module")
def demo_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("maze_demos")
    cotpc_main(["demos", "maze", "--out", str(out), "--train", "60", "--test", "20", "--seed", "0"])
    return out


def test_files_follow_the_maniskill3_format(demo_dir):
    for split, n in (("train", 60), ("test", 20)):
        info = json.loads((demo_dir / f"{split}.json").read_text())
        assert info["env_info"]["env_id"] == "cotpc/MovingMaze-v0"
        assert info["env_info"]["max_episode_steps"] == HORIZON
        assert len(info["episodes"]) == n
        for record in info["episodes"]:
            assert {"episode_id", "reset_kwargs", "control_mode", "elapsed_steps"} <= set(record)
            assert split_of_seed(record["reset_kwargs"]["seed"]) == split
        data = load_trajectories(demo_dir / f"{split}.h5")
        assert data.obs_dim == 10 and data.action_dim == 2
        for ep in data.episodes:
            assert ep.success[-1] and not ep.success[:-1].any()
            assert ep.extras["key_steps"].shape == (5,)


def test_every_demo_replays_to_success_within_the_horizon(demo_dir):
    env = gym.make("cotpc/MovingMaze-v0")
    for split in ("train", "test"):
        data = load_trajectories(demo_dir / f"{split}.h5")
        for ep in data.episodes:
            obs, _ = env.reset(**ep.reset_kwargs)
            np.testing.assert_allclose(obs, ep.obs[0], rtol=0, atol=1e-5)
            for t, action in enumerate(ep.actions):
                obs, _, terminated, truncated, info = env.step(action)
                np.testing.assert_allclose(obs, ep.obs[t + 1], rtol=0, atol=1e-4)
                if terminated or truncated:
                    break
            assert info["success"], f"{split} episode {ep.episode_id} failed on replay"
            assert t == ep.num_steps - 1 and ep.num_steps <= HORIZON
            assert info["region_transitions"] == 5


def test_demos_are_suboptimal_planner_paths(demo_dir):
    data = load_trajectories(demo_dir / "train.h5")
    lengths = np.array([ep.num_steps for ep in data.episodes])
    assert lengths.max() <= min(5 * MAX_LEG_STEPS, HORIZON)
    actions = np.concatenate([ep.actions for ep in data.episodes])
    magnitude = np.abs(actions)
    assert magnitude.min() >= STEP_MAGNITUDE[0] - 1e-6 and magnitude.max() <= STEP_MAGNITUDE[1] + 1e-6
    assert lengths.std() > 0  # random wandering, not one fixed route
    # Every config is different.
    configs = {json.dumps(ep.reset_kwargs["options"]["config"], sort_keys=True) for ep in data.episodes}
    assert len(configs) == len(data.episodes)


def test_key_steps_mark_the_region_transitions(demo_dir):
    data = load_trajectories(demo_dir / "train.h5")
    for ep in data.episodes:
        key = ep.extras["key_steps"]
        assert np.all(np.diff(key) > 0) and key[0] > 0 and key[-1] <= ep.num_steps
        state = ep.obs
        start_y = state[:, 3].astype(float)
        moving = state[:, [4, 6, 9]].astype(float)
        regions = region_of(state[:, :2].astype(float), start_y, moving)
        for r, k in enumerate(key, start=1):
            assert regions[k] == r and not (regions[:k] == r).any()


def test_moving_blocks_move_until_landed(demo_dir):
    data = load_trajectories(demo_dir / "train.h5")
    moved = 0
    for ep in data.episodes:
        positions = ep.obs[:, [4, 6, 9]]
        assert np.all(positions >= MOVING_RANGES[:, 0] - 1e-4) and np.all(positions <= MOVING_RANGES[:, 1] + 1e-4)
        # Bridge 1 moves before the agent reaches region 2 and is static afterwards.
        k = ep.extras["key_steps"][1]
        # Speed >= 1, so a step moves at least 1 except when it bounces off a range end.
        moved += np.median(np.abs(np.diff(positions[: k + 1, 0]))) >= 1.0 - 1e-4
        assert np.all(positions[k:, 0] == positions[k, 0])
    assert moved == len(data.episodes)


def test_generation_is_deterministic_and_independent_of_workers():
    a = plan_demo(7)
    b = plan_demo(7)
    np.testing.assert_array_equal(a[1], b[1])
    from cotpc.envs.maze.demos import generate
    from cotpc.envs.maze.env import seeds_for

    seeds = seeds_for("train", 4)
    one = generate(seeds, "train", workers=1)
    two = generate(seeds, "train", workers=2)
    for x, y in zip(one.episodes, two.episodes):
        np.testing.assert_array_equal(x.actions, y.actions)


def test_generate_refuses_seeds_of_another_split():
    from cotpc.envs.maze.demos import generate
    from cotpc.envs.maze.env import seeds_for

    with pytest.raises(ValueError, match="test split"):
        generate(seeds_for("test", 2), "train")


def test_planner_region_matches_the_environment():
    rng = np.random.default_rng(0)
    maze = _StaticMaze(start_y=70.0, bridge1_x=12.0, bridge2_x=40.0, target_y=8.0)
    points = rng.uniform([0, 0], [60, 80], size=(2000, 2))
    vector = region_of(points, np.full(2000, 70.0), np.tile([12.0, 40.0, 8.0], (2000, 1)))
    scalar = np.array([maze.region(x, y) for x, y in points])
    np.testing.assert_array_equal(vector, scalar)


def test_demos_for_the_moved_landing_rule(tmp_path):
    from cotpc.envs.maze.rollout import ReplayPolicy, evaluate, load_split_configs, rollout

    cotpc_main(["demos", "maze", "--out", str(tmp_path), "--train", "12", "--test", "0", "--val", "0",
                "--landing", "moved"])
    data = load_trajectories(tmp_path / "train.h5")
    assert data.env_info["env_kwargs"] == {"landing": "moved", "deadly_gaps": True, "min_action": 1.5}
    # evaluation reads the rule from the file: every demo replays to success under it...
    replay = ReplayPolicy([ep.actions for ep in data.episodes])
    assert evaluate(replay, tmp_path, "seen").success_rate == 1.0
    # ...and the same actions under the other rule mostly miss the blocks
    configs, seeds = load_split_configs(tmp_path, "seen")
    result, _ = rollout(replay, configs, seeds, "seen", landing="observed")
    assert result.success_rate < 0.5


@pytest.mark.parametrize("args, says", [
    (["maze", "--out", "X", "--train", "-3"], "cotpc demos maze: --train must be >= 0, got -3"),
    (["maze", "--out", "X", "--train", "0", "--val", "0", "--test", "0"], "are all 0: nothing to generate"),
    (["maze", "--out", "X", "--workers", "0"], "--workers must be >= 1, got 0"),
    (["maniskill", "--out", "X", "--num", "-1"], "cotpc demos maniskill: --num must be >= 0"),
    (["kitchen", "--out", "X", "--combinations", "0"], "cotpc demos kitchen: --combinations must be >= 1"),
])
def test_demos_flags_out_of_range_are_messages(tmp_path, args, says):
    args = [str(tmp_path / "out") if a == "X" else a for a in args]
    with pytest.raises(SystemExit, match=says):
        cotpc_main(["demos", *args])
    assert not (tmp_path / "out").exists()  # nothing written
