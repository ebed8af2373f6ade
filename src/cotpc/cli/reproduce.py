"""``cotpc reproduce maze``: the whole Moving Maze study in one command (see cotpc/evaluation/reproduce.py)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import tyro

# --quick: the README's main command; must finish within 15 minutes on a 2-core CPU.
# On our 2-core CPU a CoTPC iteration at the paper's batch 256 (context 20) takes ~0.75 s, so --quick trains with
# batch 64 for 1500 iterations (~5 min per policy): a first look, not the paper's 200K-iteration schedule.
# The short schedule. 128 k-means centres instead of the paper's 1024: with 1500 iterations the 1024-way centre
# classifier is far from trained; 128 was chosen on the validation configs (docs/results/maze.md).
QUICK = {"iters": 1500, "seeds": 1, "policies": ("bet", "cotpc"), "ablations": (), "batch_size": 64, "n_centres": 128}
FULL_ITERS = 20_000


@dataclass
class MazeReproduce:
    """Demos -> unsupervised subskills -> BC/DT/BeT/CoTPC (several seeds) + ablations -> seen/unseen evaluation
    -> OUT/report.md, OUT/results.json and plots. Re-running continues an interrupted run."""

    out: Path = Path("runs/maze")
    """Output directory (demos/, runs/<policy>/seed<k>/, videos/, report.md, results.json)."""
    seeds: int = 3
    """Training seeds per policy (ablation presets get one seed each)."""
    quick: bool = False
    """Small version for a first look: BeT and CoTPC, one seed, a short schedule, no ablations."""
    iters: Optional[int] = None
    """Training iterations per run (default: 20000, or 1500 with --quick)."""
    policies: Optional[tuple[str, ...]] = None
    """Policies to compare (default: bc dt bet cotpc; with --quick: bet cotpc)."""
    ablations: Optional[tuple[str, ...]] = None
    """CoTPC ablation presets, one seed each (default: all nine of the paper's Table 4; none with --quick).
    `--ablations` followed by no names runs none."""
    beta: Optional[float] = None
    """Subskill discovery beta (default: the maze default chosen in docs/subskills.md)."""
    cost: Optional[str] = None
    """Subskill segment cost, mean-cosine (the paper's) or sum-cosine (default: the maze default)."""
    train_demos: int = 400
    """Training demos (the seen configs)."""
    test_demos: int = 100
    """Test demos (the unseen configs)."""
    val_demos: int = 100
    """Validation configs (own seed range): evaluated and reported, for choosing settings without the test set."""
    batch_size: Optional[int] = None
    """Training batch size (default: the paper's 256; 64 with --quick)."""
    n_centres: Optional[int] = None
    """k-means centres of the BeT-style heads (bet, cotpc, ablations). Default: the paper's 1024 for its 200K
    iterations; 128 with --quick, chosen on the validation configs for short schedules (docs/results/maze.md)."""
    workers: int = 2
    """Processes for demo generation."""
    device: str = "auto"
    """Training device (auto: cuda if available)."""


def main(argv: list[str], prog: str) -> None:
    from cotpc.evaluation.reproduce import ABLATIONS, BASELINES, ReproduceSettings, run
    from cotpc.subskills import MAZE_DEFAULT_BETA, MAZE_DEFAULT_COST

    cfg = tyro.extras.subcommand_cli_from_dict({"maze": MazeReproduce}, args=argv, prog=prog)
    quick = QUICK if cfg.quick else {}
    settings = ReproduceSettings(
        out=cfg.out,
        seeds=quick.get("seeds", cfg.seeds),
        iters=cfg.iters or quick.get("iters", FULL_ITERS),
        policies=tuple(cfg.policies or quick.get("policies", BASELINES)),
        ablations=tuple(cfg.ablations if cfg.ablations is not None else quick.get("ablations", ABLATIONS)),
        beta=cfg.beta if cfg.beta is not None else MAZE_DEFAULT_BETA,
        cost=cfg.cost or MAZE_DEFAULT_COST,
        train_demos=cfg.train_demos,
        test_demos=cfg.test_demos,
        val_demos=cfg.val_demos,
        workers=cfg.workers,
        extra_train_args={"device": cfg.device, "batch_size": cfg.batch_size or quick.get("batch_size"),
                          "n_centres": cfg.n_centres or quick.get("n_centres")},
    )
    results = run(settings)
    print()
    print(f"{'policy':<14}{'seen %':>10}{'unseen %':>10}")
    for name, r in results.items():
        if name != "meta":
            print(f"{name:<14}{r['seen']['mean']:>10.1f}{r['unseen']['mean']:>10.1f}")
    print(f"\nreport: {cfg.out / 'report.md'}")
    videos = sorted((cfg.out / "videos").glob("*/*.gif"))
    if videos:
        print(f"video:  {videos[-1]}")
