"""``cotpc demos {maze,maniskill}``: generate demonstrations in ManiSkill3's trajectory format."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Optional

import tyro


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


def run_maze(cfg: MazeDemos) -> dict[str, Path]:
    from cotpc.demos.maze import write_splits

    return write_splits(cfg.out, cfg.train, cfg.test, val=cfg.val, seed=cfg.seed, workers=cfg.workers,
                        landing=cfg.landing)


@dataclass
class ManiSkillDemos:
    """ManiSkill3 demos (needs `pip install -e '.[maniskill]'`): the official motion planner runs headless, its
    pd_joint_pos actions are converted by ManiSkill's converter to --control-mode with state observations, and
    only demos that succeed after conversion are kept. Writes OUT/train.{h5,json} (seeds 0.., the 'seen' seeds)
    and OUT/test.{h5,json} (seeds 2000000.., the 'unseen' seeds). Saves progress every few demos; re-running the
    same command resumes (or extends a finished split to a larger --num)."""

    env: str = "StackCube-v1"
    """ManiSkill3 task with a motion-planning solution: StackCube-v1, PegInsertionSide-v1, PickCube-v1,
    PushCube-v1, ... (the paper used 500 Stack Cube and 1000 Peg Insertion demos)."""
    out: Path = Path("data/maniskill")
    """Output directory."""
    num: int = 500
    """Number of (successful) training demos."""
    test: int = 100
    """Number of test demos, from the disjoint test seed range (their seeds are the 'unseen' evaluation set)."""
    control_mode: Literal["pd_joint_delta_pos", "pd_ee_delta_pose"] = "pd_joint_delta_pos"
    """Action space of the converted demos."""
    procs: int = 1
    """Processes planning and converting in parallel (the demos are identical for any number)."""
    offset: int = 0
    """Start this far into each split's seed range."""
    max_attempts: Optional[int] = None
    """Give up on a split after this many seeds (default 3 * N + 50)."""
    progress: bool = True
    """Show progress bars."""


def run_maniskill(cfg: ManiSkillDemos) -> dict[str, Path]:
    from cotpc.demos.maniskill import write_splits  # mani_skill is imported only here: an optional extra

    return write_splits(cfg.env, cfg.out, cfg.num, cfg.test, control_mode=cfg.control_mode, procs=cfg.procs,
                        offset=cfg.offset, max_attempts=cfg.max_attempts, progress=cfg.progress)


def main(argv: list[str], prog: str) -> None:
    cfg = tyro.extras.subcommand_cli_from_dict({"maze": MazeDemos, "maniskill": ManiSkillDemos}, args=argv, prog=prog)
    if isinstance(cfg, MazeDemos):
        run_maze(cfg)
    elif isinstance(cfg, ManiSkillDemos):
        run_maniskill(cfg)
