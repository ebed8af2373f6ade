"""Environments, one folder each: ``envs/<name>/`` holds everything the package knows about one benchmark.

- ``env.py``: the environment (or the settings of someone else's), its id and horizon, its seed ranges, its
  defaults (context, K, beta, cost), rule options and the paper's numbers, declared as an
  :class:`~cotpc.envs.spec.EnvSpec` and registered on import (with gymnasium too, for our own ids);
- ``demos.py``: how to make demos (the demonstrator and its ``cotpc demos NAME`` config);
- ``rollout.py``: how to load a split's configs and roll a policy out (``cotpc eval`` on a run of the task).

``env.py`` sits at the bottom of the package and imports nothing of it but :mod:`cotpc.envs.spec`; ``demos.py`` and
``rollout.py`` sit at the layer of training and evaluation (they write trajectory files, load policies), so nothing
below them imports them (tests/test_layout.py ranks modules by that role). Each task's study, a thin declaration
over the generic runner, is ``cotpc/studies/<name>.py``.

Importing this package registers every environment in :data:`TASKS`: ``cotpc/MovingMaze-v0`` and
``cotpc/FrankaKitchenOrdered-v0`` with gymnasium, and every :class:`~cotpc.envs.spec.EnvSpec` (including the
ManiSkill3 tasks') with :mod:`cotpc.envs.spec`. Neither mujoco nor mani_skill is imported.
"""

import importlib

from cotpc.envs.spec import EnvSpec, SeedRanges, TaskDefaults, env_spec, task_defaults

# The registry: one name per environment folder. Adding a benchmark is envs/<name>/ and one name here (and its
# study, cotpc/studies/<name>.py, found by the same name).
TASKS = ("maze", "maniskill", "kitchen")

for _name in TASKS:
    importlib.import_module(f"cotpc.envs.{_name}.env")

# The embedded default, by the names the README and SPEC use.
from cotpc.envs.maze.env import ENV_ID as MAZE_ENV_ID  # noqa: E402
from cotpc.envs.maze.env import MazeConfig, MovingMazeBatch, MovingMazeEnv, sample_config  # noqa: E402

__all__ = ["MAZE_ENV_ID", "TASKS", "EnvSpec", "MazeConfig", "MovingMazeBatch", "MovingMazeEnv", "SeedRanges",
           "TaskDefaults", "env_spec", "sample_config", "task_defaults"]
