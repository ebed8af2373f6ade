"""What the rest of the package needs to know about an environment, declared once by the environment's own
module and found by its id.

Each environment's ``env.py`` (``envs/maze/env.py``: Moving Maze; ``envs/maniskill/env.py``: the ManiSkill3 tasks;
``envs/kitchen/env.py``: the ordered Franka Kitchen) declares an :class:`EnvSpec` and registers it here (and with
gymnasium, when it has an entry point); ``cli/``, ``policies/``, ``subskills/`` and ``training/`` ask
:func:`task_defaults` or :func:`env_spec` instead of testing environment ids.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import gymnasium as gym
import numpy as np


def check_flags(prog: str, at_least: int, flags: dict[str, int | None]) -> None:
    """SystemExit naming the first of ``flags`` ({"--name": value}; None: unset) below ``at_least``."""
    for flag, value in flags.items():
        if value is not None and value < at_least:
            raise SystemExit(f"{prog}: {flag} must be >= {at_least}, got {value}")


def check_demo_flags(prog: str, counts: dict[str, int], positive: dict[str, int | None],
                     non_negative: dict[str, int]) -> None:
    """``cotpc demos``' flags: ``counts`` (``{"--train": n, ...}``) each >= 0 and not all 0, ``positive`` each >= 1
    (None: unset), ``non_negative`` each >= 0; SystemExit naming the first one out of range."""
    check_flags(prog, 0, {**counts, **non_negative})
    if counts and not any(counts.values()):
        raise SystemExit(f"{prog}: {', '.join(counts)} are all 0: nothing to generate")
    check_flags(prog, 1, positive)


@dataclass(frozen=True)
class SeedRanges:
    """Disjoint seed ranges per split, so a policy is never evaluated on 'unseen' seeds it was trained on:
    ``seeds(split, num, offset)`` hands out consecutive seeds of one split, ``check(seed, split)`` raises unless
    the seed belongs to that split. Every environment uses this one mechanism."""

    ranges: dict[str, tuple[int, int]]

    def __post_init__(self):
        spans = sorted(self.ranges.values())
        for (lo1, hi1), (lo2, _) in zip(spans, spans[1:]):
            if hi1 > lo2:
                raise ValueError(f"seed ranges overlap: {self.ranges}")

    def range(self, split: str) -> tuple[int, int]:
        if split not in self.ranges:
            raise ValueError(f"unknown split {split!r}; expected one of {sorted(self.ranges)}")
        return self.ranges[split]

    def seeds(self, split: str, num: int, offset: int = 0) -> np.ndarray:
        lo, hi = self.range(split)
        if num < 0 or offset < 0 or lo + offset + num > hi:
            raise ValueError(f"{num} seeds at offset {offset} do not fit the {split} range [{lo}, {hi})")
        return np.arange(lo + offset, lo + offset + num)

    def split_of(self, seed: int) -> str:
        for split, (lo, hi) in self.ranges.items():
            if lo <= seed < hi:
                return split
        raise ValueError(f"seed {seed} is outside every split range {self.ranges}")

    def check(self, seed: int, split: str) -> None:
        if self.split_of(int(seed)) != split:
            raise ValueError(f"seed {seed} belongs to the {self.split_of(int(seed))} split, not {split}")


# Train, validation and test configurations of every environment (each environment may declare its own).
DEFAULT_SEEDS = SeedRanges({"train": (0, 1_000_000), "val": (1_000_000, 2_000_000), "test": (2_000_000, 3_000_000)})


@dataclass(frozen=True)
class TaskDefaults:
    """Settings that depend on the task: the policy's context and k-means centres, and subskill discovery's
    penalty and segment cost."""

    context: int = 10
    """Context size T (paper: 10 ManiSkill and kitchen, 20 maze)."""
    n_centres: int = 128
    """k-means centres K of the BeT-style heads (paper: 128 ManiSkill, 1024 maze and kitchen)."""
    beta: float = 0.05
    """Subskill discovery penalty per segment (paper: 0.05 single-arm, 0.02 dual-arm)."""
    cost: str = "mean-cosine"
    """Subskill segment cost (the paper's mean-cosine, or sum-cosine)."""


# Data whose env_id no module registers (a user's own demos): the paper's single-arm ManiSkill settings.
GENERIC = TaskDefaults()


@dataclass(frozen=True)
class EnvSpec:
    """An environment as the generic parts of the package see it."""

    env_id: str
    horizon: int
    """Evaluation horizon in steps."""
    defaults: TaskDefaults
    seeds: SeedRanges = DEFAULT_SEEDS
    paper_success: dict[str, float] = field(default_factory=dict)
    """The paper's success rates (%) by policy, for reports."""
    entry_point: str | None = None
    """``module:Class`` registered with gymnasium under ``env_id`` (None: the id is someone else's, as ManiSkill3's
    are). A string, so registering imports nothing heavy (mujoco is imported when a kitchen env is made)."""


SPECS: dict[str, EnvSpec] = {}


def register(spec: EnvSpec) -> EnvSpec:
    """Make ``spec`` findable by its id, and ``gym.make``-able if it has an entry point (each environment module
    registers its own on import)."""
    SPECS[spec.env_id] = spec
    if spec.entry_point and spec.env_id not in gym.registry:
        gym.register(id=spec.env_id, entry_point=spec.entry_point, max_episode_steps=spec.horizon)
    return spec


def env_spec(env_id: str | None) -> EnvSpec | None:
    """The registered spec of ``env_id``, or None."""
    import cotpc.envs  # noqa: F401  (the environment modules register their specs on import)

    return SPECS.get(env_id) if env_id else None


def task_defaults(env_id: str | None) -> TaskDefaults:
    """The task's defaults, or :data:`GENERIC` for an environment no module registers."""
    spec = env_spec(env_id)
    return spec.defaults if spec else GENERIC
