"""DART-style ManiSkill demos (`cotpc demos maniskill --action-noise`): the Recorder executes noisy arm actions and
records the clean ones. Checked on a stand-in environment, so the main suite needs no ManiSkill3."""

import gymnasium as gym
import numpy as np
import pytest
import torch

from cotpc.envs.maniskill.demos import ManiSkillDemos, Recorder, _generation_key, make_demos


class Spy(gym.Env):
    """Remembers the actions it executes; 3-dim arm + gripper actions, 2-dim observations."""

    observation_space = gym.spaces.Box(-1, 1, (2,))
    action_space = gym.spaces.Box(-1, 1, (4,))

    def __init__(self):
        self.executed = []

    def reset(self, seed=None, options=None):
        return np.zeros(2, np.float32), {}

    def step(self, action):
        self.executed.append(np.asarray(action.detach().numpy() if hasattr(action, "detach") else action, np.float32))
        return np.zeros(2, np.float32), 0.0, False, False, {"success": np.array([False])}


def record(noise: float, seed: int, actions):
    rec = Recorder(Spy(), record_obs=True, action_noise=noise)
    rec.reset(seed=seed)
    for a in actions:
        rec.step(a)
    return np.stack(rec.actions), np.stack(rec.env.executed).reshape(len(actions), -1)


@pytest.mark.parametrize("as_tensor", [False, True])  # ManiSkill's converter passes tensors
def test_noisy_arm_clean_record(as_tensor):
    clean = np.tile(np.array([0.5, -0.2, 0.95, -1.0], np.float32), (50, 1))
    actions = [torch.tensor(a)[None] if as_tensor else a for a in clean]
    recorded, executed = record(0.1, seed=3, actions=actions)
    assert np.array_equal(recorded, clean)  # the label is the converter's action
    assert np.array_equal(executed[:, -1], clean[:, -1])  # the gripper is never perturbed
    noise = executed[:, :-1] - clean[:, :-1]
    assert 0.05 < noise[:, :2].std() < 0.15 and np.abs(executed).max() <= 1.0  # clipped to the action range
    again, executed_again = record(0.1, seed=3, actions=actions)
    assert np.array_equal(executed_again, executed)  # a function of the episode's seed
    assert not np.array_equal(record(0.1, seed=4, actions=actions)[1], executed)
    assert np.array_equal(record(0.0, seed=3, actions=actions)[1], clean)  # off: executed as given


def test_noise_is_part_of_the_generation_key_and_checked():
    assert "action_noise" not in _generation_key("StackCube-v1", "pd_joint_delta_pos", "train", 0)  # files as before
    assert _generation_key("StackCube-v1", "pd_joint_delta_pos", "train", 0, 0.1)["action_noise"] == 0.1
    with pytest.raises(SystemExit, match="--action-noise must be a std >= 0"):
        make_demos(ManiSkillDemos(action_noise=-0.1))
