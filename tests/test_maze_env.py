"""The Moving Maze rules, one by one."""

import gymnasium as gym
import numpy as np
import pytest

import cotpc.envs  # noqa: F401  (registers the env)
from cotpc.envs import MAZE_ENV_ID
from cotpc.envs.maze.env import (
    HORIZON,
    MOVING_RANGES,
    SEED_RANGES,
    PAPER_MIN_ACTION,
    RULES,
    MazeConfig,
    MazeRules,
    MovingMazeBatch,
    check_seed,
    region_of,
    sample_config,
    seeds_for,
    split_of_seed,
)


# The mechanics tests below move by small steps and into gaps, which the paper's rules (the default) raise or
# punish: they run under the forgiving rules unless they test a rule.
FORGIVING = dict(deadly_gaps=False, min_action=0.0)


def make_config(**overrides) -> MazeConfig:
    base = dict(
        agent_start=(55.0, 70.0),
        start_y=70.0,
        bridge1_x=15.0,
        bridge2_x=45.0,
        target_y=10.0,
        velocities=(1.5, 1.5, 1.5),
    )
    base.update(overrides)
    return MazeConfig(**base)


def test_registered_and_spaces():
    env = gym.make(MAZE_ENV_ID)
    obs, info = env.reset(seed=0)
    assert obs.shape == (10,) and obs.dtype == np.float32
    assert env.action_space.shape == (2,)
    assert env.spec.max_episode_steps == HORIZON
    assert info["success"] is False


def test_the_paper_rules_are_the_default():
    # "both components in [1.5, 4]" and "cannot cross the borders of the maze (but will not die from doing so)":
    # a border is safe, a gap is not.
    assert MazeRules() == RULES["paper"] == MazeRules(deadly_gaps=True, min_action=PAPER_MIN_ACTION)
    env = gym.make(MAZE_ENV_ID).unwrapped
    assert (env.deadly_gaps, env.min_action) == (True, 1.5)
    batch = MovingMazeBatch([make_config()])
    assert (batch.deadly_gaps, batch.min_action) == (True, 1.5)
    assert RULES["forgiving"] == MazeRules(**FORGIVING)
    assert [r.name for r in RULES.values()] == list(RULES)
    assert MazeRules(True, 2.0).name == "deadly-gaps-min-action2"


def test_border_blocks_the_move_without_ending_the_episode():
    env = MovingMazeBatch([make_config(agent_start=(59.0, 70.0))], **FORGIVING)
    obs, success, done = env.step([[3.0, 0.0]])  # would end at x=62, outside the maze
    np.testing.assert_allclose(obs[0, :2], [59.0, 70.0])
    assert not done[0]
    obs, _, _ = env.step([[-3.0, 0.0]])  # moving back inside works
    np.testing.assert_allclose(obs[0, :2], [56.0, 70.0])


def test_gap_blocks_the_move_unless_a_bridge_is_there():
    # Agent on the top island just above the gap; bridge 1 far to the left (x in [5, 15]).
    cfg = make_config(agent_start=(55.0, 61.0), start_y=64.0, bridge1_x=10.0)
    env = MovingMazeBatch([cfg], **FORGIVING)
    env.agent[0] = (40.0, 61.0)
    obs, _, _ = env.step([[0.0, -3.0]])  # y=58 above the middle of the gap, no bridge at x=40
    np.testing.assert_allclose(obs[0, :2], [40.0, 61.0])
    env.agent[0] = (12.0, 61.0)
    bridge_before = env.moving[0, 0]
    obs, _, _ = env.step([[bridge_before - 12.0, -3.0]])  # onto the bridge centre column
    np.testing.assert_allclose(obs[0, :2], [bridge_before, 58.0])


def test_block_freezes_once_landed_and_moves_before():
    cfg = make_config(bridge1_x=15.0, velocities=(2.0, 1.0, 1.0))
    env = MovingMazeBatch([cfg])
    env.agent[0] = (15.0, 61.0)
    xs = [env.moving[0, 0]]
    env.step([[0.0, 0.0]])
    xs.append(env.moving[0, 0])
    assert xs[1] == pytest.approx(xs[0] + 2.0)  # moving before landing
    landing_x = env.moving[0, 0]
    env.agent[0] = (landing_x, 61.0)
    env.step([[0.0, -3.0]])  # lands on the bridge
    assert env.frozen[0, 0]
    for _ in range(10):
        env.step([[0.0, 0.0]])
        assert env.moving[0, 0] == landing_x
    assert not env.frozen[0, 1] and not env.frozen[0, 2]


def test_speeds_and_ranges_bounce_inside_the_range():
    configs = [sample_config(np.random.default_rng(s)) for s in range(50)]
    env = MovingMazeBatch(configs, horizon=10_000, **FORGIVING)
    env.agent[:] = (55.0, 70.0)  # parked on the start square: never touches a moving block
    previous = env.moving.copy()
    speeds = np.abs(env.velocity).copy()
    for _ in range(300):
        env.step(np.zeros((50, 2)))
        assert np.all(env.moving >= MOVING_RANGES[:, 0] - 1e-9) and np.all(env.moving <= MOVING_RANGES[:, 1] + 1e-9)
        step = np.abs(env.moving - previous)
        # Away from the range ends a block moves exactly its speed; at a reflection it moves less.
        assert np.all(step <= speeds + 1e-9)
        far = (np.abs(previous - MOVING_RANGES[:, 0]) > 2) & (np.abs(previous - MOVING_RANGES[:, 1]) > 2)
        np.testing.assert_allclose(step[far], speeds[far])
        previous = env.moving.copy()
    assert np.all((speeds >= 1.0) & (speeds <= 2.0))
    assert not env.frozen.any()


def test_sampled_configs_cover_the_ranges():
    configs = [sample_config(np.random.default_rng(s)) for s in range(500)]
    b1 = np.array([c.bridge1_x for c in configs])
    ty = np.array([c.target_y for c in configs])
    assert b1.min() < 6 and b1.max() > 24 and ty.min() < 1 and ty.max() > 19
    for c in configs:
        c.validate()


def test_actions_are_clipped_to_four():
    env = MovingMazeBatch([make_config(agent_start=(55.0, 70.0))])
    obs, _, _ = env.step([[-100.0, 7.0]])
    np.testing.assert_allclose(obs[0, :2], [51.0, 74.0])


def test_success_inside_the_target_terminates():
    cfg = make_config(target_y=10.0, velocities=(1.0, 1.0, 1.0))
    env = gym.make(MAZE_ENV_ID)
    env.reset(seed=0, options={"config": cfg.to_dict()})
    batch = env.unwrapped._batch
    batch.agent[0] = (13.0, batch.moving[0, 2])
    target_y = batch.moving[0, 2]
    obs, reward, terminated, truncated, info = env.step(np.array([-4.0, 0.0]))
    assert info["success"] and terminated and not truncated and reward == 1.0
    assert obs[9] == target_y  # the target froze under the agent
    assert info["region_transitions"] == 0  # teleported here: no transitions were walked


def test_time_limit_truncates_at_the_horizon():
    env = gym.make(MAZE_ENV_ID)
    env.reset(seed=1)
    for t in range(HORIZON):
        _, _, terminated, truncated, _ = env.step(np.zeros(2, np.float32))
    assert truncated and not terminated


def test_reset_is_deterministic_and_config_round_trips():
    env = gym.make(MAZE_ENV_ID)
    rng = np.random.default_rng(0)
    actions = rng.uniform(-4, 4, size=(30, 2))
    runs = []
    for _ in range(2):
        obs, _ = env.reset(seed=123)
        traj = [obs] + [env.step(a)[0] for a in actions]
        runs.append(np.array(traj))
    np.testing.assert_array_equal(runs[0], runs[1])
    cfg = env.unwrapped.config
    obs, _ = env.reset(options={"config": cfg.to_dict()})
    np.testing.assert_array_equal(obs, runs[0][0])
    other, _ = env.reset(seed=124)
    assert not np.array_equal(other, runs[0][0])


def test_batched_equals_single_envs():
    configs = [sample_config(np.random.default_rng(s)) for s in range(20)]
    batch = MovingMazeBatch(configs)
    singles = [MovingMazeBatch([c]) for c in configs]
    rng = np.random.default_rng(1)
    for _ in range(HORIZON):
        actions = rng.uniform(-4, 4, size=(20, 2))
        obs, success, _ = batch.step(actions)
        for i, env in enumerate(singles):
            o, s, _ = env.step(actions[i : i + 1])
            np.testing.assert_array_equal(obs[i], o[0])
            assert success[i] == s[0]


def test_bad_actions_get_clear_errors():
    env = MovingMazeBatch([make_config()])
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros((1, 3)))
    with pytest.raises(ValueError, match="finite"):
        env.step([[np.nan, 0.0]])
    gym_env = gym.make(MAZE_ENV_ID)
    gym_env.reset(seed=0)
    with pytest.raises(ValueError, match="shape"):
        gym_env.step(np.zeros(3))
    with pytest.raises(ValueError, match="finite"):
        gym_env.step(np.array([np.inf, 0.0]))


def test_bad_config_gets_a_clear_error():
    with pytest.raises(ValueError, match="bridge1_x"):
        MazeConfig.from_dict({**make_config().to_dict(), "bridge1_x": 40.0})
    with pytest.raises(ValueError, match="invalid Moving Maze config"):
        MazeConfig.from_dict({"start_y": 70.0})


def test_seed_ranges_are_disjoint_and_enforced():
    ranges = sorted(SEED_RANGES.values())
    assert all(a[1] <= b[0] for a, b in zip(ranges, ranges[1:]))
    train, test = seeds_for("train", 400), seeds_for("test", 100)
    assert not set(train) & set(test)
    assert all(split_of_seed(int(s)) == "test" for s in test)
    with pytest.raises(ValueError):
        check_seed(int(test[0]), "train")
    with pytest.raises(ValueError):
        seeds_for("train", 10, offset=SEED_RANGES["train"][1])


def test_regions_follow_the_route():
    cfg = make_config(bridge1_x=15.0, bridge2_x=45.0, target_y=10.0)
    env = MovingMazeBatch([cfg])
    points = np.array([[55, 70], [40, 70], [10, 70], [15, 55], [10, 40], [50, 40], [45, 25], [50, 10], [20, 10], [5, 10]])
    n = len(points)
    regions = region_of(points.astype(float), np.full(n, env.start_y[0]), np.repeat(env.moving, n, 0))
    np.testing.assert_array_equal(regions, [0, 0, 1, 2, 2, 3, 4, 4, 5, 5])


def test_render_returns_an_rgb_array():
    env = gym.make(MAZE_ENV_ID)
    env.reset(seed=0)
    frame = env.render()
    assert frame.dtype == np.uint8 and frame.shape == (320, 240, 3)
    assert len(np.unique(frame.reshape(-1, 3), axis=0)) >= 4  # background, islands, blocks, agent


def test_deadly_gaps_rule_ends_the_episode_on_a_step_into_a_gap():
    cfg = make_config(bridge1_x=10.0)
    for deadly in (False, True):
        env = MovingMazeBatch([cfg], deadly_gaps=deadly)
        env.agent[0] = (40.0, 61.0)
        _, success, done = env.step([[0.0, -3.0]])  # into the gap: no bridge at x=40
        assert not success[0]
        assert done[0] == deadly and env.fallen[0] == deadly
        # where the fatal step would have landed is kept for diagnostics (NaN when no step fell)
        np.testing.assert_array_equal(env.fall_point[0], [41.5, 58.0] if deadly else [np.nan, np.nan])  # x raised to 1.5
        if deadly:  # a fallen agent stays done: later actions change nothing
            before = env.agent.copy()
            env.step([[0.0, 3.0]])
            np.testing.assert_array_equal(env.agent, before)
            np.testing.assert_array_equal(env.fall_point[0], [41.5, 58.0])
    # The maze border never kills, under either rule.
    env = MovingMazeBatch([make_config(agent_start=(59.0, 70.0))], deadly_gaps=True)
    _, _, done = env.step([[3.0, 0.0]])
    assert not done[0] and not env.fallen[0]


def test_deadly_gaps_in_the_gym_env():
    env = gym.make(MAZE_ENV_ID, deadly_gaps=True)
    env.reset(seed=0, options={"config": make_config(bridge1_x=10.0).to_dict()})
    env.unwrapped._batch.agent[0] = (40.0, 61.0)
    _, reward, terminated, truncated, info = env.step(np.array([0.0, -3.0]))
    assert terminated and not truncated and reward == 0.0 and info["fell"] and not info["success"]


def test_min_action_rule_raises_small_components_keeping_their_sign():
    # On the top island, far from every edge: a small move becomes a move of at least 1.5 per component.
    actions = np.array([[0.1, -0.2], [0.0, 0.0], [-3.0, 2.5], [-9.0, 0.5]])
    env = MovingMazeBatch([make_config(agent_start=(30.0, 70.0))] * 4, min_action=1.5)
    obs, _, _ = env.step(actions)
    np.testing.assert_allclose(obs[:, :2] - [30.0, 70.0], [[1.5, -1.5], [1.5, 1.5], [-3.0, 2.5], [-4.0, 1.5]])
    assert (env.raised_components, env.active_components) == (5, 8)
    # The forgiving rule moves by the (clipped) action itself: the agent can creep or stand still.
    env = MovingMazeBatch([make_config(agent_start=(30.0, 70.0))] * 4, **FORGIVING)
    obs, _, _ = env.step(actions)
    np.testing.assert_allclose(obs[:, :2] - [30.0, 70.0], [[0.1, -0.2], [0.0, 0.0], [-3.0, 2.5], [-4.0, 0.5]], atol=1e-5)
    for bad in (-1.0, 4.5):
        with pytest.raises(ValueError, match="min_action"):
            MovingMazeBatch([make_config()], min_action=bad)
    env = gym.make(MAZE_ENV_ID, min_action=1.5)
    env.reset(seed=0, options={"config": make_config().to_dict()})
    env.unwrapped._batch.agent[0] = (30.0, 70.0)
    obs, *_ = env.step(np.array([0.0, -0.5]))
    np.testing.assert_allclose(obs[:2], [31.5, 68.5])


def test_landing_rule_moved_checks_where_the_blocks_will_be():
    # Bridge 1 spans x in [5, 15] at x=10 and moves right by 2 per step. A step down to x=6 lands on it as
    # observed, but after the bridge has moved (x in [7, 17]) that point is in the gap.
    cfg = make_config(bridge1_x=10.0, velocities=(2.0, 1.5, 1.5))
    for landing, lands in (("observed", True), ("moved", False)):
        env = MovingMazeBatch([cfg], landing=landing, **FORGIVING)
        env.agent[0] = (6.0, 61.0)
        obs, _, _ = env.step([[0.0, -3.0]])
        assert (obs[0, 1] == 58.0) == lands, landing
    # Under "moved" the agent lands where the bridge will be, and the bridge stops there for good.
    env = MovingMazeBatch([cfg], landing="moved", **FORGIVING)
    env.agent[0] = (16.0, 61.0)  # beyond the observed bridge (x <= 15), within the moved one (x <= 17)
    obs, _, _ = env.step([[0.0, -3.0]])
    np.testing.assert_allclose(obs[0, :2], [16.0, 58.0])
    assert env.frozen[0, 0] and obs[0, 4] == 12.0
    obs, _, _ = env.step([[0.0, 0.0]])
    assert obs[0, 4] == 12.0
    with pytest.raises(ValueError, match="landing"):
        MovingMazeBatch([cfg], landing="later")
    assert gym.make(MAZE_ENV_ID, landing="moved").unwrapped.landing == "moved"
