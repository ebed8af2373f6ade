"""Demonstration data: ManiSkill3 trajectory files and training datasets."""

from cotpc.data.trajectories import (
    Episode,
    TrajectoryFormatError,
    TrajectorySet,
    load_trajectories,
    save_trajectories,
    write_episode_datasets,
)

__all__ = [
    "Episode",
    "TrajectoryFormatError",
    "TrajectorySet",
    "load_trajectories",
    "save_trajectories",
    "write_episode_datasets",
]
