"""The ``kitchen`` task suite: the paper's ordered Franka Kitchen variant (``cotpc/FrankaKitchenOrdered-v0``).

``cotpc demos kitchen`` writes demos from the scripted demonstrator (:mod:`cotpc.envs.kitchen.demos`); ``cotpc eval`` on a
kitchen run reports the success rate and the average number of sub-tasks completed in order
(:mod:`cotpc.envs.kitchen.rollout`). ``cotpc reproduce kitchen`` is the paper's study: demos -> subskills (scored
against the demonstrator's sub-task boundaries) -> BC/DT/BeT/CoTPC x seeds -> the paper's two numbers on
seen / val / unseen configs -> OUT/results.json and OUT/report.md, on the generic runner of
:mod:`cotpc.studies.runs`. Importing this module imports neither mujoco nor gymnasium_robotics (the command line
imports every suite module to build its help).
"""

from __future__ import annotations

import functools
import json
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from cotpc.data.trajectories import load_trajectories, save_trajectories
from cotpc.envs.kitchen.demos import KitchenDemos, generate, make_demos, print_report, write_splits
from cotpc.envs.kitchen.env import ENV_ID, HORIZON, PAPER_AVG_COMPLETED, PAPER_SUCCESS
from cotpc.envs.spec import task_defaults
from cotpc.envs.kitchen.rollout import evaluate, evaluate_run, load_split_configs
from cotpc.subskills.labeling import label_file
from cotpc.training.train import TrainConfig, resolve_device
from cotpc.studies.runs import (Evaluation, check_study_flags, cpu_count, describe_hardware, fresh_eval, plot_learning_curves,
                                provenance, stats, train_and_evaluate)
from cotpc.studies.suites import Suite, register_suite

SPLITS = ("seen", "val", "unseen")
DEMO_FILES = {"seen": "train", "val": "val", "unseen": "test"}  # split -> demo file holding its configs


@dataclass
class KitchenReproduce:
    """The paper's Franka Kitchen study (needs `pip install -e '.[kitchen]'`): scripted demos -> unsupervised
    subskills (scored against the demonstrator's sub-task boundaries) -> BC/DT/BeT/CoTPC (several seeds) -> success
    rate and average completed sub-tasks on seen / val / unseen configs -> OUT/report.md, OUT/results.json.
    Re-running continues (demos, finished runs and their evaluations on disk are reused)."""

    out: Path = Path("runs/kitchen")
    """Output directory (demos/, runs/<policy>/seed<k>/, report.md, results.json)."""
    seeds: int = 3
    """Training seeds per policy."""
    iters: int = 20_000
    """Training iterations per run."""
    policies: tuple[str, ...] = ("bc", "dt", "bet", "cotpc")
    """Policies to train and compare (any preset, e.g. dp)."""
    train_demos: int = 50
    """Training demos (the paper's 50; their scenes are the seen configs)."""
    val_demos: int = 10
    """Validation configs (own seed range), for choosing settings without the test configs."""
    test_demos: int = 90
    """Test configs (the paper's 90 unseen configs)."""
    demo_seed: int = 0
    """Seed of the demos (draws the ordered combinations; cotpc demos kitchen --seed)."""
    batch_size: Optional[int] = None
    """Training batch size (default: the paper's, 256; bc 32)."""
    n_centres: Optional[int] = None
    """k-means centres of the BeT-style heads (default: the task's, the paper's 1024)."""
    jobs: int = 1
    """Training runs at once, each in its own process with cores / jobs threads."""
    device: str = "auto"
    """Training and evaluation device (auto: cuda if available)."""
    bf16: Optional[bool] = None
    """bf16 autocast for every run (`cotpc train --bf16`; default: each run times its own step in both precisions
    and picks the faster, which on a busy machine can differ between runs)."""


def reproduce(cfg: KitchenReproduce) -> dict:
    """``cotpc reproduce kitchen``: run the study of the flags, print a summary."""
    t_start = time.perf_counter()
    out = Path(cfg.out)
    demos = out / "demos"
    template = TrainConfig(data=demos / "train.h5", iters=cfg.iters, device=cfg.device, batch_size=cfg.batch_size,
                           n_centres=cfg.n_centres, bf16=cfg.bf16)
    check_study_flags("cotpc reproduce kitchen",  # an unknown policy or bad flag fails here, not after the demos
                      template, cfg.policies, {"--seeds": cfg.seeds, "--jobs": cfg.jobs, "--train-demos": cfg.train_demos},
                      env_ids=(ENV_ID,))
    defaults = task_defaults(ENV_ID)
    write_missing_demos(demos, {"train": cfg.train_demos, "val": cfg.val_demos, "test": cfg.test_demos},
                        cfg.demo_seed)
    print(f"[2/5] subskill discovery, {defaults.cost} cost, beta={defaults.beta}", flush=True)
    subskills, _ = label_file(demos / "train.h5", beta=defaults.beta, min_size=1, cost=defaults.cost)
    if "precision" in subskills:
        print(f"[2/5] demonstrator sub-task boundaries within +-{subskills['tol']} steps: precision "
              f"{subskills['precision']:.3f}, recall {subskills['recall']:.3f}", flush=True)

    splits = [split for split in SPLITS if (demos / f"{DEMO_FILES[split]}.h5").exists()]
    evaluations = {split: Evaluation(cached=functools.partial(cached_eval, split=split, demos=demos),
                                     evaluate=functools.partial(evaluate_split, split=split, demos=demos))
                   for split in splits}

    def print_run(name: str, seed: int, run_dir: Path, summaries: dict) -> None:
        print(f"[4/5] {name} seed {seed}: " + "  ".join(
            f"{split} {100 * x['success_rate']:.1f}% / {x['mean_completed']:.2f}" for split, x in summaries.items()),
            flush=True)

    device = resolve_device(cfg.device)
    runs = [(name, seed) for name in cfg.policies for seed in range(cfg.seeds)]
    grid = train_and_evaluate(out, template, runs, evaluations,
                              jobs=cfg.jobs, device=device, step="[3/5]", after_run=print_run)
    results: dict = {
        name: {split: {**stats([100 * x["success_rate"] for x in per_split[split]]),
                       "completed": stats([x["mean_completed"] for x in per_split[split]])}
               for split in splits}
        for name, per_split in grid.summaries.items()
    }
    results["meta"] = {
        **provenance("mujoco", "gymnasium-robotics"),
        "settings": {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(cfg).items()},
        "n_centres": cfg.n_centres or defaults.n_centres,
        "context": defaults.context,
        "subskills": subskills,
        "wall_seconds": round(time.perf_counter() - t_start, 1),  # this invocation (finished runs are reused)
        "train_seconds_total": round(sum(t for t in grid.train_seconds.values() if t), 1),
        "train_seconds": grid.train_seconds,
        "horizon": HORIZON,
        "success_unit": "percent of episodes; completed: sub-tasks completed in order per rollout, of 4",
        "checkpoint_selection": "final weights of a fixed schedule (no selection on evaluation success)",
        "paper": {"split": "unseen", "success": PAPER_SUCCESS, "avg_completed": PAPER_AVG_COMPLETED},
    }
    (out / "results.json").write_text(json.dumps(results, indent=1))
    print("[5/5] report", flush=True)
    write_report(results, out)
    print()
    print(f"{'policy':<10}{'seen %':>9}{'unseen %':>10}{'unseen completed':>18}")
    for name, r in results.items():
        if name != "meta" and "unseen" in r:
            print(f"{name:<10}{r['seen']['mean']:>9.1f}{r['unseen']['mean']:>10.1f}"
                  f"{r['unseen']['completed']['mean']:>18.2f}")
    print(f"\nreport: {out / 'report.md'}")
    return results


def write_missing_demos(demos: Path, counts: dict[str, int], seed: int) -> None:
    """Write the splits of ``counts`` (train / val / test -> demos) that are not on disk. Validation and test
    configs use the training demos' ordered combinations: when the training file is on disk, they are read from
    it (in the order they were drawn, which is the order they first appear)."""
    missing = {split: n for split, n in counts.items() if n > 0 and not (demos / f"{split}.h5").exists()}
    if not missing:
        return
    print(f"[1/5] demos ({', '.join(missing)}) -> {demos}", flush=True)
    if "train" in missing:
        write_splits(demos, missing["train"], missing.get("test", 0), val=missing.get("val", 0), seed=seed)
        return
    combos: list[tuple[str, ...]] = []
    for ep in load_trajectories(demos / "train.h5", extras=()).episodes:
        tasks = tuple(ep.reset_kwargs["options"]["tasks"])
        if tasks not in combos:
            combos.append(tasks)
    for split, n in missing.items():
        trajectories, report = generate(split, n, combos, offset=seed)
        save_trajectories(demos / split, trajectories)
        print_report(report)


def evaluate_split(run_dir: Path, load, split: str, demos: Path) -> dict:
    """Evaluate ``load()``'s policy on the configs of ``split``; write ``run_dir/eval_<split>.json``."""
    r = evaluate(load(), demos, split)
    r.meta.update({"run": str(run_dir), "checkpoint": "last", "demos": str(demos)})
    r.to_json(run_dir / f"eval_{split}.json")
    return r.summary()


def cached_eval(run_dir: Path, split: str, demos: Path) -> dict | None:
    """The summary of ``eval_<split>.json`` if it was written after the current weights, on exactly the split's
    configs (scene seeds and requested orders) and the full horizon; else None (evaluate again)."""
    saved = fresh_eval(run_dir, f"eval_{split}.json")
    try:
        configs = [(e["seed"], tuple(e["tasks"])) for e in saved["episodes"]]
        same = configs == load_split_configs(demos, split) and saved["summary"]["horizon"] == HORIZON
    except (KeyError, TypeError):
        return None
    return saved["summary"] if same else None


def write_report(results: dict, out: Path) -> Path:
    """``OUT/report.md``: success rate and average completed sub-tasks per split, beside the paper's numbers."""
    meta = results["meta"]
    s = meta["settings"]
    sub = meta["subskills"]
    policies = [p for p in results if p != "meta"]
    splits = [split for split in SPLITS if policies and split in results[policies[0]]]
    lines = [
        "# Franka Kitchen results (the paper's ordered variant)",
        "",
        f"Command: `{meta.get('command') or 'cotpc reproduce kitchen'}`  ",
        f"{s['train_demos']} training demos (seen configs), {s['val_demos']} validation configs, {s['test_demos']} "
        f"test configs (unseen), {s['iters']} training iterations per run at batch "
        f"{s['batch_size'] or 'default (256; bc 32)'}, {meta['n_centres']} k-means centres, context "
        f"{meta['context']}, {s['seeds']} seed(s) per policy, horizon {meta['horizon']}.  ",
        f"Checkpoints: {meta['checkpoint_selection']}.  ",
        f"Training {meta['train_seconds_total'] / 60:.1f} min in all, this invocation {meta['wall_seconds'] / 60:.1f} "
        f"min, on {describe_hardware(meta['hardware'])}; torch "
        f"{meta['versions']['torch']}, mujoco {meta['versions']['mujoco']}, gymnasium-robotics "
        f"{meta['versions']['gymnasium_robotics']}.",
        "",
        "Success rate (%, all 4 requested sub-tasks in the requested order) / average number of sub-tasks completed "
        "in order (of 4): mean ± std over seeds, best seed in brackets. The paper's numbers are on unseen configs.",
        "",
        "| policy | " + " | ".join(f"{split} success | {split} completed" for split in splits)
        + " | paper success | paper completed |",
        "|---|" + "---|---|" * len(splits) + "---|---|",
    ]

    def cell(r, digits):
        return f"{r['mean']:.{digits}f} ± {r['std']:.{digits}f} [{r['best']:.{digits}f}]"

    for p in policies:
        r = results[p]
        lines.append(f"| {p} | " + " | ".join(f"{cell(r[split], 1)} | {cell(r[split]['completed'], 2)}"
                                              for split in splits)
                     + f" | {meta['paper']['success'].get(p, '–')} | {meta['paper']['avg_completed'].get(p, '–')} |")
    lines += [
        "",
        f"Subskills: {sub['cost']} cost, beta {sub['beta']}, {sub['subskills_mean']:.2f} per demo (mean length "
        f"{sub['length_mean']:.1f} actions).",
    ]
    if "precision" in sub:
        lines[-1] += (f" Against the demonstrator's sub-task boundaries (within ±{sub['tol']} steps): precision "
                      f"{sub['precision']:.3f}, recall {sub['recall']:.3f}, F1 {sub['f1']:.3f} "
                      f"({sub['matched']} of {sub['true']} boundaries found, {sub['predicted']} predicted).")
    if policies:
        figure = plot_learning_curves(out / "runs", policies, out / "learning_curves.png")
        lines += ["", f"![learning curves]({figure.name})"]
    path = out / "report.md"
    path.write_text("\n".join(lines) + "\n")
    return path


SUITE = register_suite(Suite(
    name="kitchen", owns=lambda env_id: env_id == ENV_ID, demos=KitchenDemos, make_demos=make_demos,
    evaluate=evaluate_run, reproduce=KitchenReproduce, run_study=reproduce,
))
