"""Moving Maze: the paper's 2-D s-shaped maze with moving bridges and a moving target.

Layout (y up, 60 wide x 80 tall; every choice the paper leaves open is in docs/moving-maze.md)::

    y=80 +--------------------------+----+
         |  top island  [0,50]      |start|  start square: x in [50,60], centre y in [60,80] (static)
    y=60 +--+====+------------------+----+
            |br1 |  bridge 1: 10x10, y in [50,60], centre x moves in [5,25]
    y=50 +--+====+-----------------------+
         |  middle island [0,60]         |
    y=30 +-----------------------+====+--+
                                 |br2 |     bridge 2: 10x10, y in [20,30], centre x moves in [35,55]
    y=20 +----+------------------+====+--+
         |tgt |  bottom island [10,60]   |  target: x in [0,10], centre y moves in [0,20]
    y=0  +----+--------------------------+

All state lives in :class:`MovingMazeBatch`, which steps many configurations at once with numpy;
:class:`MovingMazeEnv` is the gymnasium view of one of them. Both share one implementation of the rules.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import gymnasium as gym
import numpy as np

from cotpc.envs.spec import DEFAULT_SEEDS, EnvSpec, TaskDefaults, register

WIDTH, HEIGHT = 60.0, 80.0
MAX_ACTION = 4.0  # each action component is clipped to [-4, 4]
PAPER_MIN_ACTION = 1.5  # the paper: "both components in [1.5, 4]" (the default min_action rule)
ENV_ID = "cotpc/MovingMaze-v0"
HORIZON = 60  # evaluation horizon (paper: "maximum number of steps as 60")
BLOCK = 10.0  # squares and bridges are 10 x 10
SPEED_RANGE = (1.0, 2.0)

# Static islands as (x0, x1, y0, y1), closed rectangles.
ISLANDS = np.array(
    [
        [0.0, 50.0, 60.0, 80.0],  # top
        [0.0, 60.0, 30.0, 50.0],  # middle
        [10.0, 60.0, 0.0, 20.0],  # bottom
    ]
)
START_X = 55.0  # start square centre x (right of the top island)
BRIDGE1_Y, BRIDGE2_Y = 55.0, 25.0  # bridge centres y (they span the 10-high gaps)
TARGET_X = 5.0  # target centre x (left of the bottom island)
# Ranges of the block centres (each 20 wide, as in the paper).
START_Y_RANGE = (60.0, 80.0)
BRIDGE1_X_RANGE = (5.0, 25.0)
BRIDGE2_X_RANGE = (35.0, 55.0)
TARGET_Y_RANGE = (0.0, 20.0)
# Moving blocks, in this order everywhere: bridge 1 (moves in x), bridge 2 (x), target (y).
MOVING_RANGES = np.array([BRIDGE1_X_RANGE, BRIDGE2_X_RANGE, TARGET_Y_RANGE])
MOVING_NAMES = ("bridge1", "bridge2", "target")

# Region ids along the route; regions are the islands cut vertically in the middle (see region_of).
NUM_REGIONS = 6
ISLAND_SPLIT_X = (25.0, 30.0, 35.0)  # top, middle, bottom

# Seeds of configurations: disjoint ranges per split, enforced by seeds_for / check_seed.
SEEDS = DEFAULT_SEEDS
SEED_RANGES = SEEDS.ranges
seeds_for = SEEDS.seeds  # num configuration seeds of a split, starting offset into its range
split_of_seed = SEEDS.split_of
check_seed = SEEDS.check  # raise unless the seed belongs to the split (keeps train, val and test disjoint)
OBS_DIM, ACTION_DIM = 10, 2
LANDING_RULES = ("observed", "moved")  # when the blocks move within a step (see MovingMazeBatch)


@dataclass(frozen=True)
class MazeRules:
    """The two rules the paper states that a reconstruction could read more forgivingly (docs/moving-maze.md).

    The defaults are the paper's: the agent "cannot cross the borders of the maze (but will not die from doing
    so)", so a border is safe and a gap is not (``deadly_gaps``); the actions have "both components in [1.5, 4]"
    (``min_action``: each component's magnitude is raised to at least 1.5). The demos are valid under all rules.
    """

    deadly_gaps: bool = True
    """A step into a gap ends the episode as a failure (False: the step is blocked)."""
    min_action: float = PAPER_MIN_ACTION
    """Each action component's magnitude is raised to at least this, sign kept (0: any action up to 4)."""

    @property
    def name(self) -> str:
        """The name of these rules in :data:`RULES` (``paper``, ``forgiving``, ...), or a descriptive one."""
        for name, rules in RULES.items():
            if rules == self:
                return name
        return f"{'deadly' if self.deadly_gaps else 'safe'}-gaps-min-action{self.min_action:g}"


# Named rule sets: the paper's (the default) and the forgiving readings, kept for comparison.
RULES = {
    "paper": MazeRules(deadly_gaps=True, min_action=PAPER_MIN_ACTION),
    "any-action": MazeRules(deadly_gaps=True, min_action=0.0),  # deadly gaps, any action up to 4
    "safe-gaps": MazeRules(deadly_gaps=False, min_action=PAPER_MIN_ACTION),  # a step into a gap is blocked
    "forgiving": MazeRules(deadly_gaps=False, min_action=0.0),  # both (this project's default before 2026-12)
}


@dataclass
class MazeConfig:
    """Everything that defines one episode: initial positions and signed block velocities."""

    agent_start: tuple[float, float]
    start_y: float
    bridge1_x: float
    bridge2_x: float
    target_y: float
    velocities: tuple[float, float, float]  # signed speeds of bridge1 (x), bridge2 (x), target (y)

    def to_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict) -> "MazeConfig":
        try:
            cfg = cls(
                agent_start=tuple(float(v) for v in d["agent_start"]),
                start_y=float(d["start_y"]),
                bridge1_x=float(d["bridge1_x"]),
                bridge2_x=float(d["bridge2_x"]),
                target_y=float(d["target_y"]),
                velocities=tuple(float(v) for v in d["velocities"]),
            )
        except (KeyError, TypeError, ValueError) as e:
            raise ValueError(f"invalid Moving Maze config {d!r}: {e}") from None
        cfg.validate()
        return cfg

    def validate(self) -> None:
        checks = [
            (START_Y_RANGE, self.start_y, "start_y"),
            (BRIDGE1_X_RANGE, self.bridge1_x, "bridge1_x"),
            (BRIDGE2_X_RANGE, self.bridge2_x, "bridge2_x"),
            (TARGET_Y_RANGE, self.target_y, "target_y"),
        ]
        for (lo, hi), value, name in checks:
            if not lo <= value <= hi:
                raise ValueError(f"Moving Maze config: {name}={value} outside [{lo}, {hi}]")
        if len(self.velocities) != 3 or not all(SPEED_RANGE[0] <= abs(v) <= SPEED_RANGE[1] for v in self.velocities):
            raise ValueError(f"Moving Maze config: speeds {self.velocities} must have magnitude in {SPEED_RANGE}")
        ax, ay = self.agent_start
        if not (WIDTH - BLOCK <= ax <= WIDTH and self.start_y - BLOCK / 2 <= ay <= min(self.start_y + BLOCK / 2, HEIGHT)):
            raise ValueError(f"Moving Maze config: agent_start {self.agent_start} is not inside the start square")


def sample_config(rng: np.random.Generator) -> MazeConfig:
    """A random configuration: block centres uniform in their ranges, speeds in [1, 2], random directions."""
    start_y = rng.uniform(*START_Y_RANGE)
    agent = (rng.uniform(WIDTH - BLOCK, WIDTH), rng.uniform(start_y - BLOCK / 2, min(start_y + BLOCK / 2, HEIGHT)))
    speeds = rng.uniform(*SPEED_RANGE, size=3) * rng.choice([-1.0, 1.0], size=3)
    return MazeConfig(
        agent_start=(float(agent[0]), float(agent[1])),
        start_y=float(start_y),
        bridge1_x=float(rng.uniform(*BRIDGE1_X_RANGE)),
        bridge2_x=float(rng.uniform(*BRIDGE2_X_RANGE)),
        target_y=float(rng.uniform(*TARGET_Y_RANGE)),
        velocities=tuple(float(v) for v in speeds),
    )


# ----------------------------------------------------------------------------------------------------------------
# Geometry, vectorised over a batch: points (B, 2), start_y (B,), moving block positions (B, 3).


def block_rects(start_y: np.ndarray, moving: np.ndarray) -> np.ndarray:
    """(B, 4, 4) rectangles (x0, x1, y0, y1) of start square, bridge 1, bridge 2 and target."""
    h = BLOCK / 2
    b1, b2, ty = moving[:, 0], moving[:, 1], moving[:, 2]
    ones = np.ones_like(start_y)
    return np.stack(
        [
            np.stack([ones * (WIDTH - BLOCK), ones * WIDTH, start_y - h, start_y + h], -1),
            np.stack([b1 - h, b1 + h, ones * (BRIDGE1_Y - h), ones * (BRIDGE1_Y + h)], -1),
            np.stack([b2 - h, b2 + h, ones * (BRIDGE2_Y - h), ones * (BRIDGE2_Y + h)], -1),
            np.stack([ones * 0.0, ones * BLOCK, ty - h, ty + h], -1),
        ],
        axis=1,
    )


def inside(points: np.ndarray, rects: np.ndarray) -> np.ndarray:
    """points (B, 2), rects (B, R, 4) or (R, 4) -> (B, R) closed-rectangle membership."""
    x, y = points[:, 0:1], points[:, 1:2]
    return (rects[..., 0] <= x) & (x <= rects[..., 1]) & (rects[..., 2] <= y) & (y <= rects[..., 3])


def in_bounds(points: np.ndarray) -> np.ndarray:
    """(B,) whether each point is inside the maze's outer border."""
    return (points[:, 0] >= 0) & (points[:, 0] <= WIDTH) & (points[:, 1] >= 0) & (points[:, 1] <= HEIGHT)


def walkable(points: np.ndarray, start_y: np.ndarray, moving: np.ndarray) -> np.ndarray:
    """(B,) whether each point is inside the maze and on an island or a green block."""
    on_island = inside(points, ISLANDS).any(1)
    on_block = inside(points, block_rects(start_y, moving)).any(1)
    return in_bounds(points) & (on_island | on_block)


def region_of(points: np.ndarray, start_y: np.ndarray, moving: np.ndarray) -> np.ndarray:
    """(B,) region id 0..5 along the route, -1 if not walkable.

    Islands are cut vertically in the middle; each bridge belongs to the island below it; the start square belongs
    to region 0 (top right) and the target to region 5 (bottom left).
    """
    on_island = inside(points, ISLANDS)
    on_block = inside(points, block_rects(start_y, moving))
    x = points[:, 0]
    region = np.full(len(points), -1)
    # Later assignments win: islands first, then blocks (a bridge belongs to the island below it).
    region = np.where(on_island[:, 0], np.where(x < ISLAND_SPLIT_X[0], 1, 0), region)
    region = np.where(on_island[:, 1], np.where(x < ISLAND_SPLIT_X[1], 2, 3), region)
    region = np.where(on_island[:, 2], np.where(x < ISLAND_SPLIT_X[2], 5, 4), region)
    region = np.where(on_block[:, 0], 0, region)
    region = np.where(on_block[:, 1], 2, region)
    region = np.where(on_block[:, 2], 4, region)
    region = np.where(on_block[:, 3], 5, region)
    return region


def advance_blocks(moving: np.ndarray, velocity: np.ndarray, frozen: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One step of constant-speed back-and-forth motion, reflecting at the range ends; frozen blocks stay."""
    lo, hi = MOVING_RANGES[:, 0], MOVING_RANGES[:, 1]
    pos = moving + np.where(frozen, 0.0, velocity)
    over, under = pos > hi, pos < lo
    pos = np.where(over, 2 * hi - pos, np.where(under, 2 * lo - pos, pos))
    velocity = np.where(over | under, -velocity, velocity)
    return pos, velocity


def check_actions(actions, batch_size: int) -> np.ndarray:
    actions = np.asarray(actions, dtype=np.float64)
    if actions.shape == (ACTION_DIM,) and batch_size == 1:
        actions = actions[None]
    if actions.shape != (batch_size, ACTION_DIM):
        raise ValueError(f"Moving Maze: expected actions of shape ({batch_size}, {ACTION_DIM}), got {actions.shape}")
    if not np.all(np.isfinite(actions)):
        raise ValueError(f"Moving Maze: actions must be finite, got {actions[~np.isfinite(actions).all(1)]}")
    return actions


class MovingMazeBatch:
    """Many Moving Maze episodes stepped together (numpy, no Python loop over episodes).

    An episode that has reached the target is done: it ignores further actions and stays successful.

    ``deadly_gaps`` picks the rule for a move that ends inside the maze but off walkable ground (in a gap where
    no block is at that moment): ``True`` (default, the paper's) makes the agent fall and ends the episode as a
    failure; ``False`` leaves the agent where it is. Moves that would leave the maze are blocked under both rules (the paper:
    the agent "cannot cross the borders ... but will not die from doing so").

    ``landing`` picks when the blocks move within a step: ``"observed"`` (default) checks the move against the
    block positions the agent observed, then the blocks move; ``"moved"`` moves the blocks first, so a move must
    land where a block *will* be, which a policy can only judge from the blocks' motion over several
    observations. The demonstrator plans for either (see docs/moving-maze.md).

    ``min_action`` > 0 reads the paper's action range ("both components in [1.5, 4]") as a rule of the
    environment: each component's magnitude is raised to at least ``min_action`` (sign kept, 0 counts as
    positive), so the agent can never stand still or creep. Default 1.5 (the paper's); 0: any action up to 4 per
    component. The demonstrator's actions are already in that range, so the demos are valid under both.
    :data:`RULES` names the combinations.
    """

    def __init__(
        self, configs: list[MazeConfig], horizon: int = HORIZON, deadly_gaps: bool = True, landing: str = "observed",
        min_action: float = PAPER_MIN_ACTION,
    ):
        if not configs:
            raise ValueError("MovingMazeBatch needs at least one config")
        if landing not in LANDING_RULES:
            raise ValueError(f"landing must be one of {LANDING_RULES}, got {landing!r}")
        if not 0.0 <= min_action <= MAX_ACTION:
            raise ValueError(f"min_action must be in [0, {MAX_ACTION}], got {min_action}")
        self.configs = list(configs)
        self.horizon = horizon
        self.deadly_gaps = deadly_gaps
        self.landing = landing
        self.min_action = float(min_action)
        self.reset()

    @property
    def num_envs(self) -> int:
        return len(self.configs)

    def reset(self) -> np.ndarray:
        c = self.configs
        self.agent = np.array([cfg.agent_start for cfg in c], dtype=np.float64)
        self.start_y = np.array([cfg.start_y for cfg in c], dtype=np.float64)
        self.moving = np.array([[cfg.bridge1_x, cfg.bridge2_x, cfg.target_y] for cfg in c], dtype=np.float64)
        self.velocity = np.array([cfg.velocities for cfg in c], dtype=np.float64)
        self.frozen = np.zeros((len(c), 3), dtype=bool)
        self.success = np.zeros(len(c), dtype=bool)
        self.fallen = np.zeros(len(c), dtype=bool)
        self.fall_point = np.full((len(c), 2), np.nan)  # where the step that fell would have landed (diagnostics)
        self.elapsed = np.zeros(len(c), dtype=np.int64)
        # Action components of active episodes, and how many of them the min_action rule raised.
        self.active_components = self.raised_components = 0
        # Furthest region reached along the route (number of completed region transitions).
        self.progress = np.maximum(region_of(self.agent, self.start_y, self.moving), 0)
        return self.obs()

    def obs(self) -> np.ndarray:
        """(B, 10): agent (x, y) then the centres of start square, bridge 1, bridge 2 and target."""
        n = self.num_envs
        return np.stack(
            [
                self.agent[:, 0],
                self.agent[:, 1],
                np.full(n, START_X),
                self.start_y,
                self.moving[:, 0],
                np.full(n, BRIDGE1_Y),
                self.moving[:, 1],
                np.full(n, BRIDGE2_Y),
                np.full(n, TARGET_X),
                self.moving[:, 2],
            ],
            axis=1,
        ).astype(np.float32)

    def state(self) -> np.ndarray:
        """(B, 13) full simulator state: agent, start_y, moving positions, velocities, frozen flags."""
        return np.concatenate(
            [self.agent, self.start_y[:, None], self.moving, self.velocity, self.frozen.astype(np.float64)], axis=1
        )

    def step(self, actions) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Apply (B, 2) displacements. Returns (obs, success, done); done = success, fallen or horizon reached."""
        actions = check_actions(actions, self.num_envs)
        active = ~self.success & ~self.fallen & (self.elapsed < self.horizon)
        if self.min_action > 0:
            self.raised_components += int((np.abs(actions[active]) < self.min_action).sum())
            actions = np.where(actions >= 0, 1.0, -1.0) * np.maximum(np.abs(actions), self.min_action)
        self.active_components += int(active.sum()) * ACTION_DIM
        actions = np.clip(actions, -MAX_ACTION, MAX_ACTION)
        if self.landing == "moved":  # the blocks move first: the move is checked against where they are now
            self.moving, self.velocity = advance_blocks(self.moving, self.velocity, self.frozen | ~active[:, None])
        # With landing="observed" the move is checked against the block positions the agent observed; a move that
        # would leave walkable ground leaves the agent where it is. Every gap (>= 5) is wider than the largest step (4 per component),
        # so checking the end point is enough: no move can jump a gap.
        proposal = self.agent + actions
        ok = active & walkable(proposal, self.start_y, self.moving)
        if self.deadly_gaps:
            falls = active & ~ok & in_bounds(proposal)
            self.fallen |= falls
            self.fall_point[falls] = proposal[falls]
        self.agent = np.where(ok[:, None], proposal, self.agent)
        # A moving block the agent stands on stops for good.
        on_block = inside(self.agent, block_rects(self.start_y, self.moving))[:, 1:]
        self.frozen |= on_block & active[:, None]
        if self.landing == "observed":
            self.moving, self.velocity = advance_blocks(self.moving, self.velocity, self.frozen | ~active[:, None])
        self.success |= active & on_block[:, 2]
        self.elapsed += active
        region = region_of(self.agent, self.start_y, self.moving)
        self.progress = np.where(active & (region == self.progress + 1), region, self.progress)
        done = self.success | self.fallen | (self.elapsed >= self.horizon)
        return self.obs(), self.success.copy(), done

    def render(self, index: int = 0, scale: int = 4, path: np.ndarray | None = None) -> np.ndarray:
        return render_frame(self.agent[index], self.start_y[index], self.moving[index], scale, path)


class MovingMazeEnv(gym.Env):
    """Gymnasium interface to one Moving Maze episode.

    ``reset(seed=s)`` samples a configuration from ``s``; ``reset(seed=s, options={"config": {...}})`` rebuilds an
    exact configuration (the demos store it in ``reset_kwargs``). ``info["success"]`` is True once the agent is
    inside the target; the episode then terminates with reward 1.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(
        self, render_mode: str | None = "rgb_array", horizon: int = HORIZON, deadly_gaps: bool = True,
        landing: str = "observed", min_action: float = PAPER_MIN_ACTION,
    ):
        self.render_mode = render_mode
        self.horizon = horizon
        self.deadly_gaps = deadly_gaps
        self.landing = landing
        self.min_action = min_action
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, shape=(OBS_DIM,), dtype=np.float32)
        self.action_space = gym.spaces.Box(-MAX_ACTION, MAX_ACTION, shape=(ACTION_DIM,), dtype=np.float32)
        self._batch: MovingMazeBatch | None = None

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if options and "config" in options:
            config = MazeConfig.from_dict(options["config"])
        else:
            config = sample_config(self.np_random)
        self.config = config
        self._batch = MovingMazeBatch([config], horizon=self.horizon, deadly_gaps=self.deadly_gaps,
                                      landing=self.landing, min_action=self.min_action)
        return self._batch.obs()[0], self._info()

    def step(self, action):
        if self._batch is None:
            raise RuntimeError("call reset() before step()")
        obs, success, done = self._batch.step(check_actions(action, 1))
        terminated = bool(success[0] or self._batch.fallen[0])
        truncated = bool(done[0]) and not terminated
        return obs[0], float(success[0]), terminated, truncated, self._info()

    def _info(self) -> dict:
        b = self._batch
        return {
            "success": bool(b.success[0]),
            "fell": bool(b.fallen[0]),
            "region_transitions": int(b.progress[0]),
            "elapsed_steps": int(b.elapsed[0]),
            "state": b.state()[0],
        }

    def render(self):
        return self._batch.render(0)


# ----------------------------------------------------------------------------------------------------------------
# Rendering without a display: plain numpy rasterisation.

COLORS = {
    "background": (235, 235, 235),
    "island": (70, 110, 200),
    "block": (60, 170, 90),
    "frozen": (30, 120, 60),
    "target": (240, 180, 40),
    "agent": (220, 40, 40),
    "path": (120, 20, 20),
}


def render_frame(
    agent: np.ndarray, start_y: float, moving: np.ndarray, scale: int = 4, path: np.ndarray | None = None
) -> np.ndarray:
    """An (80*scale, 60*scale, 3) uint8 image, y up: islands blue, blocks green, target gold, agent red."""
    h, w = int(HEIGHT * scale), int(WIDTH * scale)
    img = np.empty((h, w, 3), dtype=np.uint8)
    img[:] = COLORS["background"]

    def fill(rect, color):
        x0, x1, y0, y1 = (np.clip(np.asarray(rect) * scale, 0, [w, w, h, h])).round().astype(int)
        img[h - y1 : h - y0, x0:x1] = color

    for rect in ISLANDS:
        fill(rect, COLORS["island"])
    rects = block_rects(np.array([start_y]), np.asarray(moving, dtype=np.float64)[None])[0]
    for i, rect in enumerate(rects):
        fill(rect, COLORS["target"] if i == 3 else COLORS["block"])
    if path is not None and len(path):
        for px, py in np.asarray(path):
            cx, cy = int(px * scale), int(h - py * scale)
            img[max(cy - 1, 0) : cy + 1, max(cx - 1, 0) : cx + 1] = COLORS["path"]
    yy, xx = np.mgrid[0:h, 0:w]
    cx, cy = agent[0] * scale, h - agent[1] * scale
    img[(xx - cx) ** 2 + (yy - cy) ** 2 <= (1.5 * scale) ** 2] = COLORS["agent"]
    return img


# What the rest of the package knows about Moving Maze (cotpc.envs.spec). Context 20 is the paper's. K = 1024 is
# the paper's maze BeT for its 200K iterations (short schedules choose 128 on validation configs:
# docs/results/maze.md). Subskills: sum-cosine cost with beta 1.0, chosen from the key-step recovery table in
# docs/subskills.md (never from policy success). The paper's Table 1 (unseen configs, success %).
SPEC = register(EnvSpec(
    ENV_ID, HORIZON, TaskDefaults(context=20, n_centres=1024, beta=1.0, cost="sum-cosine"), SEEDS,
    paper_success={"bc": 9.0, "dt": 23.0, "bet": 33.0, "cotpc": 44.0},
    entry_point="cotpc.envs.maze.env:MovingMazeEnv",
))
