"""Environments. Importing this module registers ``cotpc/MovingMaze-v0`` and ``cotpc/FrankaKitchenOrdered-v0`` with
gymnasium, and every environment's :class:`~cotpc.envs.spec.EnvSpec` (Moving Maze, the kitchen variant, the
ManiSkill3 tasks) with :mod:`cotpc.envs.spec`."""

import gymnasium as gym

from cotpc.envs import kitchen, maniskill  # noqa: F401  (register their specs; mujoco, mani_skill are not imported)
from cotpc.envs.moving_maze import ENV_ID as MAZE_ENV_ID
from cotpc.envs.moving_maze import HORIZON, MazeConfig, MovingMazeBatch, MovingMazeEnv, sample_config
from cotpc.envs.spec import EnvSpec, SeedRanges, TaskDefaults, env_spec, task_defaults

if MAZE_ENV_ID not in gym.registry:
    gym.register(id=MAZE_ENV_ID, entry_point="cotpc.envs.moving_maze:MovingMazeEnv", max_episode_steps=HORIZON)
if kitchen.ENV_ID not in gym.registry:  # gymnasium_robotics and mujoco are imported only when one is made
    gym.register(id=kitchen.ENV_ID, entry_point="cotpc.envs.kitchen:FrankaKitchenOrderedEnv",
                 max_episode_steps=kitchen.HORIZON)

__all__ = ["MAZE_ENV_ID", "EnvSpec", "MazeConfig", "MovingMazeBatch", "MovingMazeEnv", "SeedRanges", "TaskDefaults",
           "env_spec", "sample_config", "task_defaults"]
