"""The Moving Maze demonstrator: RRT-style planning with hindsight, as in the paper's appendix.

For one configuration seed:

1. Sample the start square, the agent's start and where each moving block (bridge 1, bridge 2, target) will be
   when the agent lands on it. Freeze the maze there: this is the *static* maze the planner sees.
2. Plan five legs, one per region transition (region 0 -> 1 -> 2 -> 3 -> 4 -> target), each with an RRT-style
   sampler of at most 13 steps whose actions have components of magnitude drawn from [1.5, 4] with the sign
   pointing towards the sample: deliberately wandering, sub-optimal paths.
3. Animate the moving blocks coherently (the hindsight): for each block, draw a speed in [1, 2] and a direction
   at the step the agent lands on it, and run the bounce dynamics backwards to find the initial position that
   puts the block exactly under the agent at that step (the block then freezes).
4. Replay the actions in the real environment from the recorded configuration and keep the demo only if it
   succeeds within the 60-step horizon (so every stored demo is a verified success).

The demonstrator also records the privileged key steps: for each region transition, the index of the first state
in the new region. They are for scoring unsupervised subskill discovery only, never for training.
"""

from __future__ import annotations

import functools

import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from dataclasses import asdict, dataclass
from typing import Literal

import numpy as np

from cotpc.data.trajectories import Episode, TrajectorySet, save_trajectories
from cotpc.envs.spec import check_demo_flags
from cotpc.envs.maze.env import (
    BLOCK,
    BRIDGE1_X_RANGE,
    BRIDGE1_Y,
    BRIDGE2_X_RANGE,
    BRIDGE2_Y,
    HEIGHT,
    HORIZON,
    ISLAND_SPLIT_X,
    ISLANDS,
    MOVING_RANGES,
    SPEED_RANGE,
    START_Y_RANGE,
    TARGET_Y_RANGE,
    WIDTH,
    MazeConfig,
    MazeRules,
    seeds_for,
    SPEC,
    MovingMazeBatch,
    check_seed,
    region_of,
)

MAX_LEG_STEPS = 13  # paper: at most 13 steps per region transition
STEP_MAGNITUDE = (1.5, 4.0)  # paper: action components in [1.5, 4]
ENV_ID = SPEC.env_id


@dataclass
class _StaticMaze:
    """The maze frozen at the planned block positions, with fast scalar geometry for the planner."""

    start_y: float
    bridge1_x: float
    bridge2_x: float
    target_y: float

    def __post_init__(self):
        h = BLOCK / 2
        self.start_rect = (WIDTH - BLOCK, WIDTH, self.start_y - h, self.start_y + h)
        self.bridge1 = (self.bridge1_x - h, self.bridge1_x + h, BRIDGE1_Y - h, BRIDGE1_Y + h)
        self.bridge2 = (self.bridge2_x - h, self.bridge2_x + h, BRIDGE2_Y - h, BRIDGE2_Y + h)
        self.target = (0.0, BLOCK, self.target_y - h, self.target_y + h)
        self.rects = [tuple(r) for r in ISLANDS.tolist()] + [self.start_rect, self.bridge1, self.bridge2, self.target]

    def walkable(self, x: float, y: float) -> bool:
        if not (0.0 <= x <= WIDTH and 0.0 <= y <= HEIGHT):
            return False
        return any(r[0] <= x <= r[1] and r[2] <= y <= r[3] for r in self.rects)

    def region(self, x: float, y: float) -> int:
        # Same rules as env.region_of, in scalar form (checked against it in the tests).
        r = -1
        top, mid, bot = ISLANDS
        if _in(top, x, y):
            r = 1 if x < ISLAND_SPLIT_X[0] else 0
        if _in(mid, x, y):
            r = 2 if x < ISLAND_SPLIT_X[1] else 3
        if _in(bot, x, y):
            r = 5 if x < ISLAND_SPLIT_X[2] else 4
        for rect, region in ((self.start_rect, 0), (self.bridge1, 2), (self.bridge2, 4), (self.target, 5)):
            if _in(rect, x, y):
                r = region
        return r


def _in(rect, x: float, y: float) -> bool:
    return rect[0] <= x <= rect[1] and rect[2] <= y <= rect[3]


def _legs(maze: _StaticMaze):
    """Per leg: allowed regions, goal test, rectangle to sample goal points in, and sampling box."""
    top, mid, _ = ISLANDS
    return [
        ({0, 1}, lambda x, y: maze.region(x, y) == 1, (top[0], ISLAND_SPLIT_X[0], top[2], top[3]), (0, 60, 55, 80)),
        ({1, 2}, lambda x, y: maze.region(x, y) == 2, maze.bridge1, (0, 50, 45, 80)),
        ({2, 3}, lambda x, y: maze.region(x, y) == 3, (ISLAND_SPLIT_X[1], mid[1], mid[2], mid[3]), (0, 60, 30, 60)),
        ({3, 4}, lambda x, y: maze.region(x, y) == 4, maze.bridge2, (20, 60, 15, 50)),
        ({4, 5}, lambda x, y: _in(maze.target, x, y), maze.target, (0, 60, 0, 30)),
    ]


def _rrt_leg(rng, maze, start, allowed, is_goal, goal_rect, box, goal_bias=0.3, max_iters=600):
    """Grow a tree from ``start`` until a node reaches the goal; return the list of actions or None."""
    nodes = np.empty((max_iters + 1, 2))
    nodes[0] = start
    parent = np.full(max_iters + 1, -1)
    depth = np.zeros(max_iters + 1, dtype=int)
    actions = np.zeros((max_iters + 1, 2))
    n = 1
    for _ in range(max_iters):
        rect = goal_rect if rng.random() < goal_bias else box
        sample = np.array([rng.uniform(rect[0], rect[1]), rng.uniform(rect[2], rect[3])])
        dist = np.sum((nodes[:n] - sample) ** 2, axis=1)
        dist[depth[:n] >= MAX_LEG_STEPS] = np.inf
        i = int(np.argmin(dist))
        if not np.isfinite(dist[i]):
            return None
        delta = sample - nodes[i]
        sign = np.where(np.abs(delta) < 1e-9, rng.choice([-1.0, 1.0], size=2), np.sign(delta))
        action = sign * rng.uniform(*STEP_MAGNITUDE, size=2)
        x, y = nodes[i] + action
        if not maze.walkable(x, y) or maze.region(x, y) not in allowed:
            continue
        nodes[n], parent[n], depth[n], actions[n] = (x, y), i, depth[i] + 1, action
        if is_goal(x, y):
            path = []
            while n > 0:
                path.append(actions[n])
                n = parent[n]
            return path[::-1]
        n += 1
    return None


def _back_simulate(position: float, velocity: float, steps: int, lo: float, hi: float) -> tuple[float, float]:
    """Initial (position, velocity) such that ``steps`` bounce steps forward end at (position, velocity)."""
    p, v = position, -velocity
    for _ in range(steps):
        p += v
        if p > hi:
            p, v = 2 * hi - p, -v
        elif p < lo:
            p, v = 2 * lo - p, -v
    return p, -v


def plan_demo(
    seed: int, max_attempts: int = 200, landing: str = "observed"
) -> tuple[MazeConfig, np.ndarray, np.ndarray, np.ndarray]:
    """Plan one verified demo for ``seed``: returns (config, obs (N+1, 10), actions (N, 2), key_steps (5,)).
    ``landing``: the environment's rule for when blocks move within a step (see MovingMazeBatch)."""
    rng = np.random.default_rng(seed)
    for _ in range(max_attempts):
        start_y = rng.uniform(*START_Y_RANGE)
        maze = _StaticMaze(
            start_y=start_y,
            bridge1_x=rng.uniform(*BRIDGE1_X_RANGE),
            bridge2_x=rng.uniform(*BRIDGE2_X_RANGE),
            target_y=rng.uniform(*TARGET_Y_RANGE),
        )
        agent = np.array([rng.uniform(WIDTH - BLOCK, WIDTH), rng.uniform(start_y - BLOCK / 2, min(start_y + BLOCK / 2, HEIGHT))])
        actions, position = [], agent.copy()
        for allowed, is_goal, goal_rect, box in _legs(maze):
            leg = _rrt_leg(rng, maze, position, allowed, is_goal, goal_rect, box)
            if leg is None:
                break
            actions += leg
            position = position + np.sum(leg, axis=0)
        else:
            if len(actions) > HORIZON:
                continue
            actions = np.array(actions)
            waypoints = agent + np.concatenate([np.zeros((1, 2)), np.cumsum(actions, axis=0)])
            config = _animate(rng, maze, agent, waypoints, landing)
            if config is None:
                continue
            result = _replay(config, actions, landing)
            if result is not None:
                obs, key_steps = result
                return config, obs, actions.astype(np.float32), key_steps
    raise RuntimeError(f"Moving Maze demonstrator: no successful demo for seed {seed} in {max_attempts} attempts")


def _animate(rng, maze: _StaticMaze, agent: np.ndarray, waypoints: np.ndarray, landing: str) -> MazeConfig | None:
    """Choose speeds, directions and initial positions so each block is under the agent when it lands."""
    # The landing move of action t is checked after t block moves ("observed") or t + 1 ("moved").
    extra = 1 if landing == "moved" else 0
    planned = [maze.bridge1_x, maze.bridge2_x, maze.target_y]
    rects = [maze.bridge1, maze.bridge2, maze.target]
    initial, velocities = [], []
    for b in range(3):
        landed = [t for t in range(len(waypoints) - 1) if _in(rects[b], *waypoints[t + 1])]
        if not landed:
            return None
        speed = rng.uniform(*SPEED_RANGE) * rng.choice([-1.0, 1.0])
        p0, v0 = _back_simulate(planned[b], speed, landed[0] + extra, *MOVING_RANGES[b])
        initial.append(float(np.clip(p0, *MOVING_RANGES[b])))
        velocities.append(float(v0))
    return MazeConfig(
        agent_start=(float(agent[0]), float(agent[1])),
        start_y=float(maze.start_y),
        bridge1_x=initial[0],
        bridge2_x=initial[1],
        target_y=initial[2],
        velocities=tuple(velocities),
    )


def _replay(config: MazeConfig, actions: np.ndarray, landing: str) -> tuple[np.ndarray, np.ndarray] | None:
    """Run the actions in the real environment; (obs, key_steps) if it succeeds exactly at the last step."""
    env = MovingMazeBatch([config], landing=landing)
    obs = [env.obs()[0]]
    regions = [int(region_of(env.agent, env.start_y, env.moving)[0])]
    for t, action in enumerate(actions):
        o, success, done = env.step(action[None])
        obs.append(o[0])
        regions.append(int(region_of(env.agent, env.start_y, env.moving)[0]))
        if done[0] and t != len(actions) - 1:
            return None
    if not env.success[0]:
        return None
    regions = np.array(regions)
    # First state index in each of regions 1..5.
    key_steps = np.array([int(np.argmax(regions == r)) if (regions == r).any() else -1 for r in range(1, 6)])
    if (key_steps < 0).any() or (np.diff(key_steps) <= 0).any():
        return None
    return np.array(obs, dtype=np.float32), key_steps


def generate(seeds: np.ndarray, split: str, workers: int = 1, landing: str = "observed") -> TrajectorySet:
    """Demos for the given configuration seeds (all must belong to ``split``)."""
    for seed in seeds:
        check_seed(int(seed), split)
    plan = functools.partial(plan_demo, landing=landing)
    if workers > 1:
        with ProcessPoolExecutor(workers) as pool:
            plans = list(pool.map(plan, [int(s) for s in seeds], chunksize=16))
    else:
        plans = [plan(int(s)) for s in seeds]
    episodes = []
    for i, (seed, (config, obs, actions, key_steps)) in enumerate(zip(seeds, plans)):
        success = np.zeros(len(actions), dtype=bool)
        success[-1] = True
        episodes.append(
            Episode(
                obs=obs,
                actions=actions,
                success=success,
                episode_id=i,
                reset_kwargs={"seed": int(seed), "options": {"config": config.to_dict()}},
                control_mode="delta_xy",
                extras={"key_steps": key_steps.astype(np.int64)},
                extra_attrs={"key_steps": {"description": "index of the first state in each new region (1..5)"}},
            )
        )
    # the rules the demos were replayed under (the paper's, MazeRules' defaults): gym.make(env_id, **env_kwargs)
    rules = asdict(MazeRules())
    env_info = {"env_id": ENV_ID, "env_kwargs": {"landing": landing, **rules}, "max_episode_steps": HORIZON}
    meta = {
        "source_type": "motion_planning",
        "source_desc": "cotpc Moving Maze demonstrator: RRT-style legs on a static maze, blocks animated in hindsight",
        "split": split,
    }
    return TrajectorySet(episodes=episodes, env_info=env_info, meta=meta)


def generate_splits(
    num_train: int, num_test: int, seed: int = 0, workers: int = 1, num_val: int = 0, landing: str = "observed"
) -> dict[str, TrajectorySet]:
    """Demos of each split from its own seed range: train (the seen configs), val (validation configs for
    selection and diagnostics) and test (the unseen configs). Splits with 0 demos are left out."""
    start = time.perf_counter()
    sizes = {"train": num_train, "val": num_val, "test": num_test}
    sets = {split: generate(seeds_for(split, n, seed), split, workers, landing) for split, n in sizes.items() if n > 0}
    for s in sets.values():
        s.meta["generation_seconds_total"] = round(time.perf_counter() - start, 3)
    return sets


def write_splits(out: Path, train: int, test: int, val: int = 0, seed: int = 0, workers: int = 1,
                 landing: str = "observed") -> dict[str, Path]:
    """Generate the splits (:func:`generate_splits`) and write each as ``out/<split>.{h5,json}``; prints a line
    per split. Returns the paths of the files written."""
    start = time.perf_counter()
    sets = generate_splits(train, test, seed=seed, workers=workers, num_val=val, landing=landing)
    paths = {}
    for split, trajectories in sets.items():
        h5_path, _ = save_trajectories(Path(out) / split, trajectories)
        lengths = np.array([ep.num_steps for ep in trajectories.episodes])
        print(f"{split}: {len(lengths)} demos -> {h5_path}  (steps mean {lengths.mean():.1f}, "
              f"min {lengths.min()}, max {lengths.max()})")
        paths[split] = h5_path
    print(f"generated in {time.perf_counter() - start:.1f} s")
    return paths


@dataclass
class MazeDemos:
    """Moving Maze demos from the RRT-style planner with hindsight; writes OUT/train.{h5,json}, OUT/val.{h5,json}
    and OUT/test.{h5,json}, each from its own disjoint seed range."""

    out: Path
    """Output directory."""
    train: int = 400
    """Number of training demos (configs from the train seed range; these are also the 'seen' configs)."""
    test: int = 100
    """Number of test demos (configs from the disjoint test seed range; the 'unseen' configs)."""
    val: int = 100
    """Number of validation demos (configs from the disjoint validation seed range): evaluate on these with
    `cotpc eval --split val` to choose settings or checkpoints without touching the test configs. 0 = none."""
    seed: int = 0
    """Offset into each split's seed range: demo i of a split uses that split's seed start + seed + i."""
    workers: int = 1
    """Processes used for planning (demos are identical for any number of workers)."""
    landing: Literal["observed", "moved"] = "observed"
    """When the blocks move within a step: 'observed' checks a move against the block positions the agent saw;
    'moved' moves the blocks first (the agent must anticipate them). Stored in the files' env_kwargs, which
    `cotpc eval` uses."""


def make_demos(cfg: MazeDemos) -> dict[str, Path]:
    """``cotpc demos maze``."""
    check_demo_flags("cotpc demos maze", {"--train": cfg.train, "--val": cfg.val, "--test": cfg.test},
                     {"--workers": cfg.workers}, {"--seed": cfg.seed})
    return write_splits(cfg.out, cfg.train, cfg.test, val=cfg.val, seed=cfg.seed, workers=cfg.workers,
                        landing=cfg.landing)
