"""DART-style ManiSkill demos (`cotpc demos maniskill --action-noise`): the Recorder executes noisy arm actions and
records the clean ones. Checked on a stand-in environment, so the main suite needs no ManiSkill3."""

import gymnasium as gym
import numpy as np
import pytest
import torch

from cotpc.envs.maniskill import demos as demos_module
from cotpc.envs.maniskill.demos import Demonstrator, ManiSkillDemos, Recorder, _generation_key, make_demos


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
    rec = Recorder(Spy(), record_obs=True, demonstrator=Demonstrator(noise))
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
    assert _generation_key("StackCube-v1", "pd_joint_delta_pos", "train", 0, Demonstrator(0.1))["action_noise"] == 0.1
    with pytest.raises(SystemExit, match="--action-noise must be a std >= 0"):
        make_demos(ManiSkillDemos(action_noise=-0.1))


class Holding(Spy):
    """Spy whose object counts as grasped from the 10th step to the 29th (its one key-state flag)."""

    def step(self, action):
        obs, reward, terminated, truncated, info = super().step(action)
        info["is_grasped"] = np.array([10 <= len(self.executed) < 30])
        return obs, reward, terminated, truncated, info


def test_grasped_noise_only_while_grasped(monkeypatch):
    monkeypatch.setitem(demos_module.KEY_STATE_FLAGS, "Holding-v0", ("is_grasped",))
    rec = Recorder(Holding(), record_obs=True, key_flags_of="Holding-v0", demonstrator=Demonstrator(0.0, 0.3))
    rec.reset(seed=5)
    clean = np.tile(np.array([0.0, 0.0, 0.0, 1.0], np.float32), (45, 1))
    for a in clean:
        rec.step(a)
    noise = np.stack(rec.env.executed)[:, :-1] - clean[:, :-1]
    # flags describe the state after each step, so steps 10..29 (grasped after steps 9..28) are noisy
    assert not noise[:10].any() and not noise[30:].any()
    assert (noise[10:30] != 0).all() and 0.15 < noise[10:30].std() < 0.45
    assert np.array_equal(np.stack(rec.actions), clean)  # the clean actions are what is recorded
    # with grasped_noise left out, the noise (and its random draws) are exactly --action-noise's
    plain = Recorder(Holding(), record_obs=True, key_flags_of="Holding-v0", demonstrator=Demonstrator(0.1))
    plain.reset(seed=5)
    for a in clean:
        plain.step(a)
    assert np.array_equal(np.stack(plain.env.executed), record(0.1, seed=5, actions=list(clean))[1])


def test_grasped_noise_is_checked_and_keyed():
    with pytest.raises(ValueError, match="needs key_flags_of"):
        Recorder(Spy(), record_obs=True, demonstrator=Demonstrator(grasped_noise=0.2))
    key = _generation_key("StackCube-v1", "pd_joint_delta_pos", "train", 0, Demonstrator(0.1, 0.0))
    assert key["grasped_noise"] == 0.0 and key["action_noise"] == 0.1  # 0 while grasped is a setting, not "off"
    assert "grasped_noise" not in _generation_key("StackCube-v1", "pd_joint_delta_pos", "train", 0, Demonstrator(0.1))
    with pytest.raises(SystemExit, match="--grasped-noise must be a std >= 0"):
        make_demos(ManiSkillDemos(grasped_noise=float("nan")))
    with pytest.raises(SystemExit, match="does not have"):
        make_demos(ManiSkillDemos(env="PushCube-v1", grasped_noise=0.2))


def test_close_holds_are_cut_to_the_steps_asked_for():
    # a planner's pd_joint_pos actions: approach, a 6-step hold after closing, a lift, a 6-step hold after opening
    approach = [[0.1 * t, 0.0, 1.0] for t in range(3)]
    hold_closed = [[0.2, 0.0, -1.0]] * 6
    lift = [[0.2, 0.1 * t, -1.0] for t in range(1, 4)]
    hold_open = [[0.2, 0.3, 1.0]] * 6
    plan = np.array(approach + hold_closed + lift + hold_open, dtype=np.float32)
    cut = demos_module.shorten_close_holds(plan, keep=2)
    assert np.array_equal(cut, np.array(approach + hold_closed[:2] + lift + hold_open, dtype=np.float32))
    assert np.array_equal(demos_module.shorten_close_holds(plan, keep=6), plan)  # the planner's own hold
    assert len(demos_module.shorten_close_holds(plan, keep=1)) == len(plan) - 5
    with pytest.raises(ValueError, match="keep must be >= 1"):
        demos_module.shorten_close_holds(plan, keep=0)


def test_close_hold_is_part_of_the_generation_key_and_checked():
    assert "close_hold" not in _generation_key("StackCube-v1", "pd_joint_delta_pos", "train", 0)  # files as before
    assert _generation_key("StackCube-v1", "pd_joint_delta_pos", "train", 0, Demonstrator(0.1, close_hold=2))["close_hold"] == 2
    with pytest.raises(SystemExit, match="--close-hold must be >= 1"):
        make_demos(ManiSkillDemos(close_hold=0))


def test_only_the_training_demos_are_altered(monkeypatch, tmp_path):
    """The validation and test splits are the planner's own for any demonstrator: their seeds are the evaluation
    sets, which must not depend on how the training demos were made."""
    made = {}
    monkeypatch.setattr(demos_module, "import_maniskill", lambda: None)
    monkeypatch.setattr(demos_module, "generate_split",
                        lambda env_id, split, n, out, demonstrator, **kw: made.setdefault(split, demonstrator))
    make_demos(ManiSkillDemos(out=tmp_path, num=3, val=2, test=2, action_noise=0.1, close_hold=2))
    assert made["train"] == Demonstrator(0.1, close_hold=2)
    assert made["val"] == made["test"] == Demonstrator()  # the planner's own


def test_holding_still_after_the_success_is_noise_free_zero_arm_deltas():
    rec = Recorder(Spy(), record_obs=True, demonstrator=Demonstrator(0.3))
    rec.reset(seed=1)
    plan = np.array([[0.5, -0.2, 0.1, -1.0], [0.4, 0.3, -0.6, 1.0]], np.float32)  # ends with the gripper opened
    for a in plan:
        rec.step(a)
    rec.hold_still(3)
    recorded, executed = np.stack(rec.actions), np.stack(rec.env.executed).reshape(5, -1)
    assert np.array_equal(recorded[:2], plan) and not np.array_equal(executed[:2], plan)  # the plan: noisy
    assert np.array_equal(recorded[2:], [[0, 0, 0, 1.0]] * 3)  # zero arm deltas, the gripper kept open
    assert np.array_equal(executed[2:], recorded[2:])  # executed as recorded: no noise while holding
    assert len(rec.obs) == 6 and len(rec.success) == 5
    assert rec.demonstrator == Demonstrator(0.3)  # the noise is back for the next demo
    with pytest.raises(ValueError, match="needs a recorded action"):
        fresh = Recorder(Spy(), record_obs=True)
        fresh.reset(seed=0)
        fresh.hold_still(2)


def test_hold_after_success_is_part_of_the_generation_key_and_checked():
    assert "hold_after_success" not in _generation_key("StackCube-v1", "pd_joint_delta_pos", "train", 0)
    key = _generation_key("StackCube-v1", "pd_joint_delta_pos", "train", 0, Demonstrator(0.1, hold_after_success=20))
    assert key["hold_after_success"] == 20
    assert "20 steps of holding still" in Demonstrator.describe(key)
    with pytest.raises(SystemExit, match="--hold-after-success must be >= 0"):
        make_demos(ManiSkillDemos(hold_after_success=-1))
