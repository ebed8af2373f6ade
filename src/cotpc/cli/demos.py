"""``cotpc demos maze``: generate demonstrations in ManiSkill3's trajectory format."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro


@dataclass
class MazeDemos:
    """Moving Maze demos from the RRT-style planner with hindsight; writes OUT/train.{h5,json}, OUT/test.{h5,json}."""

    out: Path
    """Output directory."""
    train: int = 400
    """Number of training demos (configs from the train seed range; these are also the 'seen' configs)."""
    test: int = 100
    """Number of test demos (configs from the disjoint test seed range; the 'unseen' configs)."""
    seed: int = 0
    """Offset into each split's seed range: demo i of a split uses that split's seed start + seed + i."""
    workers: int = 1
    """Processes used for planning (demos are identical for any number of workers)."""


def run_maze(cfg: MazeDemos) -> dict[str, Path]:
    from cotpc.data import save_trajectories
    from cotpc.demos.maze import generate_splits

    start = time.perf_counter()
    sets = generate_splits(cfg.train, cfg.test, seed=cfg.seed, workers=cfg.workers)
    paths = {}
    for split, trajectories in sets.items():
        if len(trajectories) == 0:
            continue
        h5_path, _ = save_trajectories(cfg.out / split, trajectories)
        lengths = np.array([ep.num_steps for ep in trajectories.episodes])
        print(
            f"{split}: {len(lengths)} demos -> {h5_path}  (steps mean {lengths.mean():.1f}, "
            f"min {lengths.min()}, max {lengths.max()})"
        )
        paths[split] = h5_path
    print(f"generated in {time.perf_counter() - start:.1f} s")
    return paths


def main(argv: list[str], prog: str) -> None:
    cfg = tyro.extras.subcommand_cli_from_dict({"maze": MazeDemos}, args=argv, prog=prog)
    if isinstance(cfg, MazeDemos):
        run_maze(cfg)
