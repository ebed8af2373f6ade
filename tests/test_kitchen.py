"""The ordered Franka Kitchen variant and its scripted demonstrator (needs the ``kitchen`` extra)."""

import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("gymnasium_robotics")
pytest.importorskip("mujoco")

from cotpc.data.trajectories import load_trajectories  # noqa: E402
from cotpc.envs.kitchen import demos  # noqa: E402
from cotpc.envs.kitchen import env as K  # noqa: E402

TASKS = ("microwave", "kettle", "light switch", "slide cabinet")


@pytest.fixture(scope="module")
def env():
    e = K.FrankaKitchenOrderedEnv()
    yield e
    e.close()


# ---- the rules, without the simulator --------------------------------------------------------------------------
def test_goal_embedding_codes_positions():
    emb = K.goal_embedding(TASKS)
    assert emb.shape == (14,) and emb.dtype == np.float32
    codes = emb.reshape(7, 2)
    for name, code in zip(K.SUBTASKS, codes):
        expected = K.ORDER_CODES[TASKS.index(name)] if name in TASKS else K.NOT_REQUESTED
        assert tuple(code) == expected, name
    assert K.decode_goal(emb) == TASKS
    # another order of the same sub-tasks is another embedding
    assert not np.array_equal(emb, K.goal_embedding(TASKS[::-1]))
    assert K.ORDER_CODES == ((0, 0), (0, 1), (1, 0), (1, 1))


@pytest.mark.parametrize("tasks, message", [
    (("microwave", "kettle", "light switch", "toaster"), "unknown sub-task"),
    (("microwave", "kettle", "microwave", "slide cabinet"), "more than once"),
    (("microwave", "kettle", "light switch"), "exactly 4"),
    (("microwave", "kettle", "light switch", "slide cabinet", "hinge cabinet"), "exactly 4"),
    ("microwave", "list of 4"),
])
def test_bad_goal_specifications_raise(tasks, message, env):
    with pytest.raises(ValueError, match=message):
        K.validate_tasks(tasks)
    with pytest.raises(ValueError, match=message):
        env.reset(seed=0, options={"tasks": tasks})
    with pytest.raises(ValueError, match=message):
        K.FrankaKitchenOrderedEnv(tasks=tasks)


def test_order_rule():
    t = K.OrderTracker(TASKS)
    assert t.update([]) == [] and not t.done
    assert t.update(["microwave"]) == ["microwave"]
    assert t.update(["microwave"]) == []  # stays counted, counted once
    # two sub-tasks finishing within one step count in the requested order
    assert t.update(["microwave", "light switch", "kettle"]) == ["kettle", "light switch"]
    assert not t.done
    assert t.update(["slide cabinet"]) == ["slide cabinet"]  # the microwave may have swung shut: still counted
    assert t.success and t.done and t.violation is None and t.completed == list(TASKS)


def test_termination_rule():
    t = K.OrderTracker(TASKS)
    t.update(["microwave"])
    t.update(["microwave", "top burner"])  # not requested
    assert t.done and not t.success and t.violation == {"task": "top burner", "reason": "not requested"}
    assert t.completed == ["microwave"]
    t = K.OrderTracker(TASKS)
    t.update(["light switch"])  # requested, but third
    assert t.done and not t.success and t.violation == {"task": "light switch", "reason": "out of order"}
    assert t.completed == []


def test_completion_rule_matches_gymnasium_robotics():
    from gymnasium_robotics.envs.franka_kitchen import kitchen_env

    assert set(K.SUBTASKS) == set(kitchen_env.OBS_ELEMENT_GOALS)
    for name in K.SUBTASKS:
        assert tuple(kitchen_env.OBS_ELEMENT_INDICES[name]) == K.QPOS_INDICES[name]
        np.testing.assert_allclose(kitchen_env.OBS_ELEMENT_GOALS[name], K.GOALS[name])
    assert kitchen_env.BONUS_THRESH == K.COMPLETION_THRESHOLD


# ---- the environment ------------------------------------------------------------------------------------------------
def test_import_does_not_need_mujoco():
    code = ("import sys, gymnasium as gym, cotpc, cotpc.envs; from cotpc.studies.suites import suites; "
            "s = suites(); assert 'kitchen' in s; assert 'cotpc/FrankaKitchenOrdered-v0' in gym.registry; "
            "assert 'mujoco' not in sys.modules and 'gymnasium_robotics' not in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True)


def test_spec_and_gym_make():
    import gymnasium as gym

    from cotpc.envs.spec import env_spec

    spec = env_spec(K.ENV_ID)
    assert spec.horizon == 280 and spec.defaults.context == 10 and spec.defaults.n_centres == 1024
    assert (spec.defaults.beta, spec.defaults.cost) == (5.0, "sum-cosine") and spec.paper_success["cotpc"] == 25.6
    for a in ("train", "val", "test"):
        for b in ("train", "val", "test"):
            if a < b:
                (lo1, hi1), (lo2, hi2) = spec.seeds.range(a), spec.seeds.range(b)
                assert hi1 <= lo2 or hi2 <= lo1
    e = gym.make(K.ENV_ID)
    assert e.spec.max_episode_steps == 280
    obs, info = e.reset(seed=1, options={"tasks": list(TASKS)})
    assert obs.shape == (44,) and e.action_space.shape == (9,)
    e.close()


def test_seeded_resets(env):
    a, info = env.reset(seed=3, options={"tasks": list(TASKS)})
    b, _ = env.reset(seed=3, options={"tasks": list(TASKS)})
    c, _ = env.reset(seed=4, options={"tasks": list(TASKS)})
    np.testing.assert_array_equal(a, b)
    assert np.abs(a[:30] - c[:30]).max() > 0.01  # another scene
    assert np.abs(a[:7] - c[:7]).max() > 0.005 and np.abs(a[23:25] - c[23:25]).max() > 0.001  # arm and kettle
    np.testing.assert_array_equal(a[30:], K.goal_embedding(TASKS))
    np.testing.assert_array_equal(c[:30], env.data.qpos[:30].astype(np.float32))  # noise-free state
    assert info["completed"] == [] and info["violation"] is None
    for seed in range(20):  # no scene starts with a sub-task done, and the arm starts clear of the kitchen
        env.reset(seed=seed)
        assert K.completed_subtasks(env.state()) == []
        robot = [i for i in range(env.data.ncon)
                 if "panda" in env.model.body(int(env.model.geom_bodyid[env.data.contact[i].geom1])).name
                 or "panda" in env.model.body(int(env.model.geom_bodyid[env.data.contact[i].geom2])).name]
        assert not robot, seed


def test_env_order_and_termination(env):
    """Completions injected into the simulator: counted in order, a violation ends the episode."""
    env.reset(seed=5, options={"tasks": list(TASKS)})
    qpos = env.data.qpos[:30].copy()
    qpos[22] = -0.75  # microwave open: first requested
    env.set_qpos(qpos)
    _, reward, terminated, truncated, info = env.step(np.zeros(9))
    assert info["completed"] == ["microwave"] and info["step_completed"] == ["microwave"] and reward == 1.0
    assert not terminated and not truncated
    qpos = env.data.qpos[:30].copy()
    qpos[19] = 0.37  # slide cabinet: requested, but fourth
    env.set_qpos(qpos)
    _, reward, terminated, _, info = env.step(np.zeros(9))
    assert terminated and not info["success"] and info["violation"]["reason"] == "out of order"
    assert info["num_completed"] == 1 and reward == 0.0

    env.reset(seed=5, options={"tasks": list(TASKS)})
    qpos = env.data.qpos[:30].copy()
    qpos[11] = -0.88  # bottom burner: not requested
    env.set_qpos(qpos)
    _, _, terminated, _, info = env.step(np.zeros(9))
    assert terminated and info["violation"] == {"task": "bottom burner", "reason": "not requested"}


def test_render_rgb_array():
    e = K.FrankaKitchenOrderedEnv(render_mode="rgb_array", width=96, height=64)
    e.reset(seed=0)
    try:
        img = e.render()
    except RuntimeError as err:  # no EGL/OSMesa on this machine: the error must say so
        assert "rendering" in str(err)
        pytest.skip(f"no headless GL here: {err}")
    assert img.shape == (64, 96, 3) and img.dtype == np.uint8 and img.std() > 1
    e.close()
    with pytest.raises(RuntimeError, match="render_mode"):
        K.FrankaKitchenOrderedEnv().render()


# ---- the demonstrator -----------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", K.SUBTASKS)
def test_demonstrator_completes_each_subtask_alone(name, env):
    others = [t for t in K.SUBTASKS if t != name][:3]
    for seed in range(3):  # the demonstrator is retried in generation too; each skill works on most scenes
        obs, _ = env.reset(seed=seed, options={"tasks": [name] + others})
        rng = np.random.default_rng(seed)
        run = demos.ScriptedRun(env, obs, rng, demos.sample_style(rng))
        try:
            demos.SKILLS[name](run)
        except demos._EpisodeOver:
            pass
        if env.tracker.completed == [name] and env.tracker.violation is None:
            assert run.key_steps[name] <= len(run.actions)
            return
    pytest.fail(f"the demonstrator did not complete {name!r} on 3 scenes")


def test_demonstrator_chain_replays():
    d = demos.Demonstrator()
    tasks = ("light switch", "bottom burner", "top burner", "kettle")
    result = d.demo(11, tasks)
    assert result is not None
    n = len(result.actions)
    assert n <= K.HORIZON and result.obs.shape == (n + 1, 44)
    assert np.all(np.diff(result.key_steps) > 0) and result.key_steps[-1] == n
    obs, infos = demos.replay(K.FrankaKitchenOrderedEnv(), 11, tasks, result.actions)
    assert len(infos) == n and infos[-1]["success"] and not any(i["success"] for i in infos[:-1])
    assert infos[-1]["completed"] == list(tasks)
    np.testing.assert_allclose(obs, result.obs, atol=1e-5)


def test_write_splits_and_replay(tmp_path):
    paths = demos.write_splits(tmp_path, train=2, val=1, test=1, num_combinations=2)
    assert set(paths) == {"train", "val", "test"}
    env = K.FrankaKitchenOrderedEnv()
    train_combos = None
    for split in ("train", "val", "test"):
        data = load_trajectories(tmp_path / f"{split}.h5")
        assert data.env_info["env_id"] == K.ENV_ID and data.env_info["max_episode_steps"] == 280
        assert data.obs_dim == 44 and data.action_dim == 9
        report = data.meta["report"]
        assert report["demos"] == len(data) and set(report["subtask_success"]) == set(K.SUBTASKS)
        combos = {tuple(ep.reset_kwargs["options"]["tasks"]) for ep in data.episodes}
        if split == "train":
            train_combos = combos
            assert len(combos) == 2
        else:
            assert combos <= train_combos  # only combinations seen in training
        for ep in data.episodes:
            seed = ep.reset_kwargs["seed"]
            K.check_seed(seed, split)
            tasks = ep.reset_kwargs["options"]["tasks"]
            np.testing.assert_array_equal(ep.obs[0, 30:], K.goal_embedding(tasks))
            assert list(ep.extras["key_steps"]) == sorted(ep.extras["key_steps"])
            assert ep.extras["key_steps"][-1] == ep.num_steps and ep.success[-1] and not ep.success[:-1].any()
            obs, infos = demos.replay(env, seed, tasks, ep.actions)  # stored actions succeed again
            assert infos[-1]["success"] and len(infos) == ep.num_steps
            np.testing.assert_allclose(obs, ep.obs, atol=1e-4)
    # evaluation: replaying the demos of a split scores 100% and 4 sub-tasks; doing nothing scores 0
    from cotpc.envs.kitchen import rollout as ev

    for split, name in (("seen", "train"), ("val", "val"), ("unseen", "test")):
        data = load_trajectories(tmp_path / f"{name}.h5")
        result = ev.evaluate(ev.ReplayPolicy([ep.actions for ep in data.episodes]), tmp_path, split)
        assert result.success.all() and (result.completed == 4).all()
        assert result.summary()["mean_completed"] == 4.0
    # a recorded rollout: frames every frame_every steps and at the end, a captioned GIF named by the outcome
    data = load_trajectories(tmp_path / "val.h5")
    result = ev.rollout(ev.ReplayPolicy([data.episodes[0].actions]), ev.load_split_configs(tmp_path, "val"), "val",
                        videos=1, video_size=32, frame_every=100)
    steps = [step for _, _, step in result.frames[0]]
    assert steps == [0, 100, 200][: len(steps) - 1] + [data.episodes[0].num_steps]
    assert result.frames[0][-1][1]["success"] and result.frames[0][-1][0].shape == (32, 32, 3)
    (gif,) = ev.write_videos(result, tmp_path / "videos")
    assert gif.name == f"seed{result.seeds[0]}_success_4of4.gif" and gif.stat().st_size > 0
    result = ev.evaluate(ev.ReplayPolicy([np.zeros((0, 9))]), tmp_path, "unseen", horizon=20)
    assert not result.success.any() and result.summary()["mean_completed"] == 0.0
    with pytest.raises(ValueError, match="check_seed|belongs to"):
        ev.check_seed(0, "test")


def test_video_caption_marks_the_requested_order_and_what_is_done():
    from cotpc.envs.kitchen import rollout as ev

    image = np.zeros((40, 120, 3), dtype=np.uint8)
    tasks = ("kettle", "microwave", "light switch", "hinge cabinet")
    green = lambda img: int(((img[..., 1] > 100) & (img[..., 0] < 60)).sum())  # noqa: E731  (the "done" colour)
    before = ev.caption(image, tasks, {"completed": [], "success": False, "violation": None}, 0)
    after = ev.caption(image, tasks, {"completed": ["kettle", "microwave"], "success": False, "violation": None}, 9)
    assert before.shape[1] == 120 and before.shape[0] > 40 and before.shape == after.shape
    np.testing.assert_array_equal(before[-40:], image)  # the frame itself is untouched, the caption above it
    assert green(before) == 0 < green(after)
