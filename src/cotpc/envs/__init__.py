"""Environments. Importing this module registers ``cotpc/MovingMaze-v0`` with gymnasium."""

import gymnasium as gym

from cotpc.envs.moving_maze import MazeConfig, MovingMazeBatch, MovingMazeEnv, sample_config

MAZE_ENV_ID = "cotpc/MovingMaze-v0"

if MAZE_ENV_ID not in gym.registry:
    gym.register(id=MAZE_ENV_ID, entry_point="cotpc.envs.moving_maze:MovingMazeEnv", max_episode_steps=60)

__all__ = ["MAZE_ENV_ID", "MazeConfig", "MovingMazeBatch", "MovingMazeEnv", "sample_config"]
