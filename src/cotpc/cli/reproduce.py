"""``cotpc reproduce {maze,maniskill}``: a whole study in one command (see cotpc/studies/)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Optional

import tyro

# --quick: the README's main command. A CoTPC iteration at the paper's batch 256 (context 20) takes 0.75 s on a
# 2-core Xeon and 1.5 s on a 2-core AVX2 EPYC (docs/performance.md), so --quick trains with batch 64 for 1500
# iterations (5-16 min per policy): a first look, not the paper's 200K-iteration schedule.
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
    """Training and evaluation device (auto: cuda if available)."""
    jobs: int = 1
    """Training runs at once, each in its own process with cores / jobs threads. One small model leaves a GPU
    mostly idle: on a 16-core GPU machine, --jobs 12 trains the whole study several times sooner."""
    keep_checkpoints: bool = False
    """Keep every tenth-of-a-run checkpoint and evaluate each on the validation configs (success against
    iterations, in results.json and val_success.png): choose a schedule without the test configs."""
    cot_weight: Optional[float] = None
    """lambda, the weight of the CoT loss of the CoT policies (default: the paper's 0.1)."""
    grad_clip: Optional[float] = None
    """Clip the global gradient norm of every run to this value (default: off, as the paper)."""


@dataclass
class ManiSkillReproduce:
    """ManiSkill3 tasks (needs `pip install -e '.[maniskill]'`): planner demos -> unsupervised subskills ->
    training of each policy and seed -> success_once / success_at_end on seen and unseen seeds ->
    OUT/report.md, OUT/results.json and learning curves. The defaults are the paper's schedule (meant for a GPU);
    re-running continues an interrupted run."""

    out: Path = Path("runs/maniskill")
    """Output directory (<task>/demos/, <task>/runs/<policy>/seed<k>/, report.md, results.json)."""
    envs: tuple[str, ...] = ("StackCube-v1", "PegInsertionSide-v1")
    """ManiSkill3 tasks with a motion planner."""
    policies: tuple[str, ...] = ("bc", "dt", "bet", "cotpc")
    """Policies to train and compare."""
    seeds: int = 3
    """Training seeds per policy."""
    iters: int = 200_000
    """Training iterations per run (the paper's 200K)."""
    batch_size: Optional[int] = None
    """Training batch size (default: the paper's, 256; bc 32)."""
    n_centres: Optional[int] = None
    """k-means centres of the BeT-style heads (default: the paper's 128 for ManiSkill)."""
    num: Optional[int] = None
    """Training demos per task (default: the paper's, 500 Stack Cube and 1000 Peg Insertion)."""
    test: int = 100
    """Test demos per task: their seeds are the unseen evaluation set."""
    seen_episodes: Optional[int] = 100
    """Evaluate seen success on the first N training seeds (default 100; 0 = all)."""
    control_mode: Literal["pd_joint_delta_pos", "pd_ee_delta_pose"] = "pd_joint_delta_pos"
    """Action space of the demos and policies."""
    horizon: Optional[int] = None
    """Steps per evaluation episode (default: the paper's, 200)."""
    procs: int = 2
    """Processes for demo generation and CPU evaluation."""
    backend: Literal["auto", "cpu", "gpu"] = "auto"
    """Evaluation simulator: gpu = ManiSkill3's GPU-parallel simulation, cpu = process pool; auto = gpu with CUDA."""
    device: str = "auto"
    """Training device (auto: cuda if available)."""


def main(argv: list[str], prog: str) -> None:
    cfg = tyro.extras.subcommand_cli_from_dict({"maze": MazeReproduce, "maniskill": ManiSkillReproduce}, args=argv,
                                               prog=prog)
    if isinstance(cfg, ManiSkillReproduce):
        return main_maniskill(cfg)
    from cotpc.studies.maze import ABLATIONS, BASELINES, ReproduceSettings, run
    from cotpc.envs.moving_maze import SPEC

    quick = QUICK if cfg.quick else {}
    settings = ReproduceSettings(
        out=cfg.out,
        seeds=quick.get("seeds", cfg.seeds),
        iters=cfg.iters or quick.get("iters", FULL_ITERS),
        policies=tuple(cfg.policies or quick.get("policies", BASELINES)),
        ablations=tuple(cfg.ablations if cfg.ablations is not None else quick.get("ablations", ABLATIONS)),
        beta=cfg.beta if cfg.beta is not None else SPEC.defaults.beta,
        cost=cfg.cost or SPEC.defaults.cost,
        train_demos=cfg.train_demos,
        test_demos=cfg.test_demos,
        val_demos=cfg.val_demos,
        workers=cfg.workers,
        jobs=cfg.jobs,
        extra_train_args={"device": cfg.device, "batch_size": cfg.batch_size or quick.get("batch_size"),
                          "n_centres": cfg.n_centres or quick.get("n_centres"),
                          "keep_checkpoints": cfg.keep_checkpoints, "cot_weight": cfg.cot_weight,
                          **({"grad_clip": cfg.grad_clip} if cfg.grad_clip is not None else {})},
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


def main_maniskill(cfg: ManiSkillReproduce) -> None:
    from cotpc.studies.maniskill import ManiSkillStudySettings, run

    results = run(ManiSkillStudySettings(
        out=cfg.out, envs=tuple(cfg.envs), policies=tuple(cfg.policies), seeds=cfg.seeds, iters=cfg.iters,
        num=cfg.num, test=cfg.test, seen_episodes=cfg.seen_episodes or None, control_mode=cfg.control_mode,
        horizon=cfg.horizon, procs=cfg.procs, backend=cfg.backend,
        extra_train_args={"device": cfg.device, "batch_size": cfg.batch_size, "n_centres": cfg.n_centres},
    ))
    print()
    print(f"{'task':<22}{'policy':<10}{'seen %':>10}{'unseen %':>10}   (success_once, mean over seeds)")
    for env_id, by_policy in results.items():
        if env_id != "meta":
            for name, r in by_policy.items():
                print(f"{env_id:<22}{name:<10}{r['seen']['mean']:>10.1f}{r['unseen']['mean']:>10.1f}")
    print(f"\nreport: {cfg.out / 'report.md'}")
