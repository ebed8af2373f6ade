"""``cotpc reproduce maniskill``: planner demos -> subskills -> training -> seen/unseen evaluation -> report,
for each ManiSkill3 task, in one command.

The layout and rules are those of ``cotpc reproduce maze`` (cotpc/studies/maze.py, cotpc/studies/runs.py): every step writes
into ``OUT/<task>/`` and is skipped when its output is complete (demo generation and training resume), and the
evaluated weights are the final ones of a fixed schedule, never selected on evaluation success.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Optional

import numpy as np
import torch

from cotpc.envs.maniskill.demos import Demonstrator, ManiSkillDemos, checked_demonstrator, make_demos, write_splits
from cotpc.envs.maniskill.env import HORIZONS, import_maniskill, is_maniskill_env
from cotpc.envs.spec import GENERIC, env_spec, task_defaults
from cotpc.envs.maniskill.rollout import evaluate, evaluate_run, policy_loader
from cotpc.studies.runs import (PROTOCOL_CHECKPOINTS, check_study_flags, Evaluation, cpu_count, describe_hardware, fresh_eval, jsonable,
                                plot_learning_curves, provenance, stats, train_and_evaluate)
from cotpc.subskills.labeling import label_file
from cotpc.training.train import TrainConfig
from cotpc.studies.suites import Suite, register_suite

# The paper's Table 2 (ManiSkill2, state observations, success %). Its Stack Cube number is on unseen configs;
# its Peg Insertion number is "0-shot" (unseen peg/hole geometries). ManiSkill3's PegInsertionSide-v1 draws the
# geometry from the seed, so our unseen seeds are unseen geometries too, but not the paper's split.
PAPER = {
    env_id: {"split": split, "results": env_spec(env_id).paper_success}  # the numbers live in the env's spec
    for env_id, split in (("StackCube-v1", "unseen"), ("PegInsertionSide-v1", "0-shot"))
}
PAPER_DEMOS = {"StackCube-v1": 500, "PegInsertionSide-v1": 1000}
SPLITS = ("seen", "unseen")


@dataclass
class ManiSkillStudySettings:
    out: Path
    envs: tuple[str, ...]
    policies: tuple[str, ...]
    seeds: int
    train: TrainConfig
    """What every run shares (schedule, batch, K, ...); its data is replaced by each task's demos/train.h5."""
    num: int | None = None  # training demos per task; None: the paper's (PAPER_DEMOS)
    test: int = 100
    val: int = 100  # validation demos: their seeds score the checkpoint curve
    seen_episodes: int | None = 100  # None: every training seed
    curve_episodes: int | None = 50  # validation seeds per kept checkpoint; None: all
    curve_every: int = 1  # score every k-th kept checkpoint (the last one always)
    paper_protocol: bool = False  # also evaluate the last PROTOCOL_CHECKPOINTS kept checkpoints on the test seeds
    jobs: int = 1
    control_mode: str = "pd_joint_delta_pos"
    horizon: int | None = None  # None: the paper's (cotpc.envs.maniskill.env.HORIZONS)
    beta: float | None = None  # None: the paper's single-arm beta
    procs: int = 2
    backend: str = "auto"
    action_noise: float = 0.0  # DART-style noise on the training demos' executed arm actions (0: the planner's)
    hold_after_success: int = 0  # still steps appended to each training demo after its success (0: none)


def run(s: ManiSkillStudySettings) -> dict:
    demonstrator = checked_demonstrator("cotpc reproduce maniskill", s.action_noise,
                                        hold_after_success=s.hold_after_success)  # flags first
    import_maniskill()
    unknown = [e for e in s.envs if e not in HORIZONS]
    if unknown:
        raise ValueError(f"not a supported ManiSkill3 task: {unknown}; supported: {sorted(HORIZONS)}")
    t_start = time.perf_counter()
    out = Path(s.out)
    results: dict = {}
    timings: dict = {}
    subskills: dict = {}
    curves: dict = {}  # env -> "<policy>/seed<k>" -> validation success of each kept checkpoint
    protocol: dict = {}  # env -> policy -> seed -> unseen success of the last kept checkpoints (paper's protocol)
    selected: dict = {}  # env -> policy -> seed -> the best validation checkpoint's unseen success (our headline)
    demo_counts = {env_id: s.num or PAPER_DEMOS.get(env_id, 500) for env_id in s.envs}
    altered = Demonstrator.describe(demonstrator.generation_key()).removeprefix("; ")  # "" for the planner's own
    altered = f" (training demos: {altered})" if altered else ""
    for env_id in s.envs:
        task = out / env_id
        demos = task / "demos"
        num = demo_counts[env_id]
        print(f"[1/4] {env_id}: {num} train + {s.val} val + {s.test} test planner demos{altered} -> {demos}",
              flush=True)
        write_splits(env_id, demos, num, s.test, control_mode=s.control_mode, procs=s.procs,
                     progress=sys.stderr.isatty(), val=s.val, demonstrator=demonstrator)
        defaults = task_defaults(env_id)  # the paper's single-arm setting
        beta, cost = (defaults.beta if s.beta is None else s.beta), defaults.cost
        print(f"[2/4] {env_id}: subskill discovery, {cost} cost, beta={beta}", flush=True)
        subskills[env_id], _ = label_file(demos / "train.h5", beta=beta, min_size=1, cost=cost)
        if "precision" in subskills[env_id]:
            sub = subskills[env_id]
            print(f"[2/4] {env_id}: the official code's privileged key states within +-{sub['tol']} steps: "
                  f"precision {sub['precision']:.3f}, recall {sub['recall']:.3f}", flush=True)
        horizon = s.horizon or HORIZONS[env_id]
        evaluations = {split: Evaluation(
            cached=functools.partial(_cached_eval, split=split, horizon=horizon,
                                     episodes=s.seen_episodes if split == "seen" else None),
            evaluate=functools.partial(_evaluate, split=split, demos=demos, s=s,
                                       episodes=s.seen_episodes if split == "seen" else None),
        ) for split in SPLITS}

        template = dataclasses.replace(s.train, data=demos / "train.h5")
        keep = template.keep_checkpoints
        curves[env_id], protocol[env_id], selected[env_id] = {}, {}, {}

        def print_run(name: str, seed: int, run_dir: Path, summaries: dict) -> None:
            if keep and s.val:
                curve = checkpoint_curve(run_dir, demos, "val", s.curve_episodes, horizon, s, every=s.curve_every)
                curves[env_id][f"{name}/seed{seed}"] = curve
                selected[env_id].setdefault(name, {})[f"seed{seed}"] = validation_selected(run_dir, curve, demos,
                                                                                           horizon, s)
            if keep and s.paper_protocol:
                protocol[env_id].setdefault(name, {})[f"seed{seed}"] = checkpoint_curve(
                    run_dir, demos, "unseen", None, horizon, s, last=PROTOCOL_CHECKPOINTS)
            print(f"[4/4] {env_id}: {name} seed {seed}: " + "  ".join(
                f"{split} {100 * summaries[split]['success_once']:.1f}% once / "
                f"{100 * summaries[split]['success_at_end']:.1f}% at end" for split in SPLITS), flush=True)

        runs = [(name, seed) for name in s.policies for seed in range(s.seeds)]
        grid = train_and_evaluate(task, template, runs, evaluations,
                                  jobs=s.jobs, step=f"[3/4] {env_id}:", after_run=print_run)
        timings.update({f"{env_id}/{run}": t for run, t in grid.train_seconds.items()})
        # "mean"/"std"/"best"/"runs" are success_once, the paper's metric (the maze results' shape);
        # success_at_end is ManiSkill3's stricter one.
        results[env_id] = {name: {split: _aggregate(grid.summaries[name][split]) for split in SPLITS}
                           for name in s.policies}
        for run, curve in curves[env_id].items():
            name, seed = run.split("/")
            results[env_id][name].setdefault("val_curve", {})[seed] = curve
        for name, by_seed in selected[env_id].items():
            results[env_id][name]["val_selected"] = {
                **stats([r["success_once"] for r in by_seed.values()]),
                "rule": "per run, the kept checkpoint of the validation curve with the highest success_once (ties: "
                        "the higher normalised reward, then the later), scored on the unseen (test) seeds: "
                        "selected on validation seeds only",
                "runs": by_seed,
            }
        for name, by_seed in protocol[env_id].items():
            results[env_id][name]["paper_protocol"] = {
                "best": max(max(c["success_once"]) for c in by_seed.values()),
                "rule": f"best over {len(by_seed)} run(s) x the last {PROTOCOL_CHECKPOINTS} kept checkpoints, "
                        "success_once on the unseen (test) seeds: selected on the test seeds",
                "runs": by_seed,
            }
    results["meta"] = {
        **provenance("mani-skill", "sapien"),
        "settings": jsonable(s),
        "demos": demo_counts,
        "horizons": {e: s.horizon or HORIZONS[e] for e in s.envs},
        "subskills": subskills,
        "wall_seconds": round(time.perf_counter() - t_start, 1),  # this invocation (finished steps are reused)
        "train_seconds": timings,
        "success_unit": "percent of episodes; mean/std/best/runs = success_once",
        "checkpoint_selection": "final weights of a fixed schedule (no selection on evaluation success)",
        "paper": PAPER,
    }
    (out / "results.json").write_text(json.dumps(results, indent=1))
    write_report(results, out)
    return results


def _aggregate(summaries: list[dict]) -> dict:
    """Per-seed evaluation summaries -> success % over seeds, stage flags % and max reward (means over seeds)."""
    return {
        **stats([100 * x["success_once"] for x in summaries]),
        "success_at_end": stats([100 * x["success_at_end"] for x in summaries]),
        "stages_once": {k: 100 * float(np.mean([x["stages_once"][k] for x in summaries]))
                        for k in summaries[0]["stages_once"]},
        "max_normalized_reward": float(np.mean([x["mean_max_normalized_reward"] for x in summaries])),
    }


def _evaluate(run_dir: Path, load, split: str, demos: Path, s: ManiSkillStudySettings, episodes: int | None) -> dict:
    """A new evaluation of ``run_dir``'s final weights on ``split``, written to ``eval_<split>.json``. ``load`` is
    unused: the evaluator loads the policy itself (one copy per process)."""
    r = evaluate(policy_loader(run_dir), demos, split, episodes, horizon=s.horizon, procs=s.procs, backend=s.backend,
                 progress=sys.stderr.isatty())
    r.meta.update({"run": str(run_dir), "checkpoint": "last", "demos": str(demos)})
    r.to_json(run_dir / f"eval_{split}.json")
    return r.summary()


def _cached_eval(run_dir: Path, split: str, horizon: int, episodes: int | None) -> dict | None:
    """The summary of ``eval_<split>.json`` if it was written after the current weights with this horizon and
    number of episodes (the seeds of a split are fixed by its demo file); else None (evaluate again)."""
    saved = fresh_eval(run_dir, f"eval_{split}.json")
    summary = saved.get("summary") if isinstance(saved, dict) else None
    if not isinstance(summary, dict):
        return None
    if summary.get("horizon") != horizon or (episodes is not None and summary.get("episodes") != episodes):
        return None
    if "stages_once" not in summary:  # written before progress was measured
        return None
    return summary


def _checkpoint_eval(ckpt: Path, split: str, demos: Path, horizon: int, s: ManiSkillStudySettings,
                     episodes: int | None) -> dict:
    """A kept checkpoint's evaluation on ``split``: the one saved beside its weights while fresh, else a new one
    (so an interrupted study picks up where it stopped)."""
    summary = _cached_eval(ckpt, split, horizon, episodes)
    return summary if summary is not None else _evaluate(ckpt, None, split=split, demos=demos, s=s, episodes=episodes)


def validation_selected(run_dir: Path, curve: dict, demos: Path, horizon: int, s: ManiSkillStudySettings) -> dict:
    """Our headline with checkpoint selection: of the checkpoints on the validation ``curve``, the one with the
    highest success_once (ties, common on a short schedule: the higher normalised reward, then the later), and
    its success on all the unseen seeds (evaluated once, saved beside its weights)."""
    n = len(curve["iteration"])
    best = max(range(n), key=lambda i: (curve["success_once"][i], curve["max_normalized_reward"][i], i))
    ckpt = run_dir / "checkpoints" / f"step_{curve['iteration'][best]:07d}"
    summary = _checkpoint_eval(ckpt, "unseen", demos, horizon, s, None)
    return {"iteration": curve["iteration"][best], "val_success_once": curve["success_once"][best],
            "success_once": 100 * summary["success_once"], "success_at_end": 100 * summary["success_at_end"],
            "max_normalized_reward": summary["mean_max_normalized_reward"]}


def checkpoint_curve(run_dir: Path, demos: Path, split: str, episodes: int | None, horizon: int,
                     s: ManiSkillStudySettings, last: int | None = None, every: int = 1) -> dict:
    """success_once and success_at_end (%) on ``split`` of each checkpoint kept under ``run_dir/checkpoints``
    (the ``last`` ones when given; every ``every``-th, counted back from the final one), with the iteration and
    the training samples it had seen. Each checkpoint's evaluation is saved beside its weights and reused while
    fresh, so an interrupted study picks up here too."""
    kept = sorted((run_dir / "checkpoints").glob("step_*"))
    kept = kept[-last:] if last else kept
    kept = kept[::-1][::max(every, 1)][::-1]
    info = json.loads((run_dir / "config.json").read_text())
    batch = info["policy"]["batch_size"]  # the effective one (the train flag is None for the preset's)
    curve: dict = {"iteration": [], "samples": [], "success_once": [], "success_at_end": [],
                   "max_normalized_reward": [], "stages_once": []}
    for ckpt in kept:
        summary = _checkpoint_eval(ckpt, split, demos, horizon, s, episodes)
        step = int(ckpt.name.split("_")[1])
        curve["iteration"].append(step)
        curve["samples"].append(step * batch)
        curve["success_once"].append(100 * summary["success_once"])
        curve["success_at_end"].append(100 * summary["success_at_end"])
        # progress short of success: it moves before success does on a short schedule
        curve["max_normalized_reward"].append(summary["mean_max_normalized_reward"])
        curve["stages_once"].append({k: 100 * v for k, v in summary["stages_once"].items()})
    return curve


def plot_val_curves(curves: dict, path: Path) -> Path:
    """Validation success_once against training samples seen, one line per run (seed 0 solid)."""
    import matplotlib  # heavy (about 1 s): imported only when a figure is drawn

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # after use("Agg"): no display needed

    fig, ax = plt.subplots(figsize=(5, 3.2))
    colours: dict = {}
    for run, c in sorted(curves.items()):
        name, seed = run.split("/")
        colour = colours.setdefault(name, f"C{len(colours)}")
        ax.plot(np.array(c["samples"]) / 1e6, c["success_once"], "o-" if seed == "seed0" else ".--", ms=3,
                color=colour, label=name if seed == "seed0" else None, lw=1.5 if seed == "seed0" else 0.8)
    ax.set_xlabel("training samples seen (millions)")
    ax.set_ylabel("val success_once (%)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def write_report(results: dict, out: Path) -> Path:
    """``OUT/report.md``: per task, success_once and success_at_end on seen and unseen seeds beside the paper."""
    meta = results["meta"]
    s = meta["settings"]
    extra = s["train"]
    lines = [
        "# ManiSkill3 results",
        "",
        f"Command: `{meta.get('command') or 'cotpc reproduce maniskill'}`  ",
        f"{extra['iters']} training iterations per run at batch {extra.get('batch_size') or 'default (256; bc 32)'}, "
        f"context {extra.get('context') or 'default (10)'}, "
        f"{extra.get('n_centres') or f'default ({GENERIC.n_centres})'} k-means centres, {s['seeds']} seed(s) per policy, "
        f"{s['control_mode']} actions, state observations"
        + (f" without dimensions {', '.join(map(str, extra['ignore_obs']))}" if extra.get("ignore_obs") else "")
        + (f"; training demos DART-style (arm noise {s['action_noise']})" if s.get("action_noise") else "")
        + (f"; training demos held still {s['hold_after_success']} steps after the success"
           if s.get("hold_after_success") else "")
        + (f"; CoT weight {extra['cot_weight']}" if extra.get("cot_weight") is not None else "")
        + (f"; offset head on the {extra['offset_from']} token" if extra.get("offset_from") else "")
        + (f"; observation std floored at {extra['obs_std_floor']:g}" if extra.get("obs_std_floor") else "")
        + f". Checkpoints: {meta['checkpoint_selection']}.  ",
        f"This invocation {meta['wall_seconds'] / 60:.1f} min on {describe_hardware(meta['hardware'])}; "
        f"torch {meta['versions']['torch']}, mani-skill {meta['versions']['mani_skill']}, "
        f"sapien {meta['versions']['sapien']}.",
        "",
        "Success (%): mean ± std over seeds, best seed in brackets. *once* = success at any step of the horizon "
        "(the paper's metric), *at end* = success at the last step (ManiSkill3's stricter one). Seen = seeds of "
        "the training demos, unseen = seeds of the test demos (a disjoint range).",
    ]

    def cell(r):
        return f"{r['mean']:.1f} ± {r['std']:.1f} [{r['best']:.1f}]"

    for env_id, by_policy in results.items():
        if env_id == "meta":
            continue
        paper = PAPER.get(env_id, {"split": "–", "results": {}})
        sub = meta["subskills"].get(env_id, {})
        lines += [
            "",
            f"## {env_id}",
            "",
            f"{meta['demos'][env_id]} training demos, horizon {meta['horizons'][env_id]}; subskills: "
            f"{sub.get('cost')} cost, beta {sub.get('beta')}, {sub.get('subskills_mean', float('nan')):.2f} per demo "
            f"(mean length {sub.get('length_mean', float('nan')):.1f} actions)." + (
                f" Against the official code's privileged key states (within ±{sub['tol']} steps): precision "
                f"{sub['precision']:.3f}, recall {sub['recall']:.3f}, F1 {sub['f1']:.3f} ({sub['matched']} of "
                f"{sub['true']} key states found, {sub['predicted']} boundaries predicted)." if "precision" in sub else ""),
            "",
            f"| policy | seen once | seen at end | unseen once | unseen at end | paper ({paper['split']}) "
            "| train min (seed 0) |",
            "|---|---|---|---|---|---|---|",
        ]
        for name, r in by_policy.items():
            t = meta["train_seconds"].get(f"{env_id}/{name}/seed0")
            lines.append(
                f"| {name} | {cell(r['seen'])} | {cell(r['seen']['success_at_end'])} | {cell(r['unseen'])} | "
                f"{cell(r['unseen']['success_at_end'])} | {paper['results'].get(name, '–')} | "
                f"{f'{t / 60:.1f}' if t else '–'} |"
            )
        stages = sorted({k for r in by_policy.values() for k in r["unseen"]["stages_once"]})
        lines += [
            "",
            "Progress on unseen seeds, short of success (mean over seeds): how often each stage flag of the task "
            "was ever true (%), and the highest normalised dense reward reached (ManiSkill3's staged reward, "
            "1 = success), averaged over episodes.",
            "",
            "| " + " | ".join(["policy", *stages, "max normalised reward"]) + " |",
            "|---|" + "---|" * (len(stages) + 1),
        ]
        for name, r in by_policy.items():
            u = r["unseen"]
            cells = [name, *(f"{u['stages_once'].get(k, float('nan')):.1f}" for k in stages),
                     f"{u['max_normalized_reward']:.3f}"]
            lines.append("| " + " | ".join(cells) + " |")
        curves = {f"{name}/{seed}": c for name, r in by_policy.items() for seed, c in r.get("val_curve", {}).items()}
        if curves:
            lines += [
                "",
                f"Validation success_once (%) of each kept checkpoint (`--keep-checkpoints`), on the first "
                f"{s.get('curve_episodes') or 'all'} validation seeds (a range disjoint from the seen and unseen "
                "ones): how success grows with the training samples seen, for choosing a schedule without the test "
                "seeds. The checkpoints are points of one cosine schedule, not runs trained to that length.",
                "",
                "| run | " + " | ".join(f"{i // 1000}K" if i % 1000 == 0 else str(i)
                                       for i in next(iter(curves.values()))["iteration"]) + " |",
                "|---|" + "---|" * len(next(iter(curves.values()))["iteration"]),
            ]
            for run, c in curves.items():
                lines.append(f"| {run} | " + " | ".join(f"{v:.0f}" for v in c["success_once"]) + " |")
            for run, c in curves.items():  # progress short of success
                if c.get("max_normalized_reward"):
                    lines.append(f"| {run}, max normalised reward | "
                                 + " | ".join(f"{v:.2f}" for v in c["max_normalized_reward"]) + " |")
            figure = plot_val_curves(curves, out / f"val_success_{env_id}.png")
            lines += ["", f"![validation success {env_id}]({figure.name})"]
        chosen = {name: r["val_selected"] for name, r in by_policy.items() if "val_selected" in r}
        if chosen:
            lines += ["", "**Validation-selected weights** (our headline with checkpoint selection: per run, the "
                          "checkpoint of the validation curve with the highest success_once, scored on the unseen "
                          "seeds), unseen success_once: "
                          + "; ".join(f"{name} {c['mean']:.1f} ± {c['std']:.1f} (iterations "
                                      + ", ".join(str(r["iteration"]) for r in c["runs"].values()) + ")"
                                      for name, c in chosen.items()) + "."]
        protocol = {name: r["paper_protocol"] for name, r in by_policy.items() if "paper_protocol" in r}
        if protocol:
            lines += ["", "**The paper's protocol** (not our number: it selects on the test seeds): "
                          + "; ".join(f"{name} {p['best']:.1f}" for name, p in protocol.items())
                          + f". Rule: {next(iter(protocol.values()))['rule']}."]
        figure = plot_learning_curves(out / env_id / "runs", list(by_policy), out / f"learning_curves_{env_id}.png")
        lines += ["", f"![learning curves {env_id}]({figure.name})"]
    path = out / "report.md"
    path.write_text("\n".join(lines) + "\n")
    return path


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
    context: Optional[int] = None
    """Context size T of the sequence policies (default: the paper's text, 10; the official code trains CoTPC on
    ManiSkill2 with 60)."""
    n_centres: Optional[int] = None
    """k-means centres of the BeT-style heads (default: the paper's 128 for ManiSkill)."""
    use_actions: Optional[bool] = None
    """Feed past actions to the transformer policies (default: the presets', True, as the paper); False
    conditions them on the states alone (`cotpc train --use-actions`; docs/results/maniskill.md, states only)."""
    cot_weight: Optional[float] = None
    """Weight of the CoT loss for the CoT policies (default: the paper's 0.1; other policies have no CoT loss).
    Stack Cube, finger velocities hidden: 1 was best on seed 0's validation, level with 0.1 over 3 seeds (results/)."""
    offset_from: Optional[Literal["state", "cot", "action"]] = None
    """The token the offset head of the k-means-headed policies reads (`cotpc train --offset-from`; default: the
    presets', the i-th CoT token for CoTPC as the paper, the state token for BeT)."""
    ignore_obs: tuple[int, ...] = ()
    """Observation dimensions the policies never see (`cotpc train --ignore-obs`; e.g. 16 17, the Panda's finger
    velocities, which make a finger bouncing off the object look like a release: docs/results/maniskill.md).
    Default: none, as the paper."""
    obs_std_floor: float = 0.0
    """Lower bound on each observation std used for normalisation (`cotpc train --obs-std-floor`; 0.01 suits
    ManiSkill's metres and radians: cube B's height otherwise reads in the thousands of stds once A is set down
    on it, docs/results/maniskill.md). Default: off, as the paper."""
    num: Optional[int] = None
    """Training demos per task (default: the paper's, 500 Stack Cube and 1000 Peg Insertion)."""
    action_noise: float = 0.0
    """DART-style training demos (`cotpc demos maniskill --action-noise`): the arm actions executed with Gaussian
    noise of this std (normalised units), the planner's corrections recorded; 0.1 is what the results in
    docs/results/maniskill.md use. The validation and test demos stay the planner's own. Default: off, as the paper."""
    hold_after_success: int = 0
    """Training demos that end with the arm held still this many steps after the success (`cotpc demos maniskill
    --hold-after-success`; 20 is what docs/results/maniskill.md uses): without them nothing shows a policy what
    to do once the task is done, and success_at_end falls short of success_once. Default: 0, as the paper."""
    test: int = 100
    """Test demos per task: their seeds are the unseen evaluation set."""
    val: int = 100
    """Validation demos per task: their seeds (a disjoint range) score the checkpoint curve of
    --keep-checkpoints, for choosing a schedule without the test seeds."""
    keep_checkpoints: bool = False
    """Keep 20 checkpoints per run, evenly spaced, and evaluate each on --curve-episodes validation seeds (a curve
    of validation success against training samples)."""
    curve_episodes: Optional[int] = 50
    """Validation seeds per kept checkpoint (0 = all of --val)."""
    curve_every: int = 1
    """Score every k-th kept checkpoint on the validation seeds (counted back from the final one): 2 halves the
    evaluation time of the curve."""
    paper_protocol: bool = False
    """With --keep-checkpoints, also evaluate the last 20 kept checkpoints on the test seeds and report the best
    (the paper's protocol, labelled: it selects on the test seeds)."""
    jobs: int = 1
    """Runs trained at once, each with cores / jobs threads (2 on a 2-core CPU: two runs side by side)."""
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
    compile: Literal["off", "default", "reduce-overhead"] = "off"
    """torch.compile every training run (`cotpc train --compile`; reduce-overhead = CUDA graphs, for a GPU)."""
    bf16: Optional[bool] = None
    """bf16 autocast for every run (`cotpc train --bf16`; default: each run times its own step in both precisions
    and picks the faster, which on a busy machine can differ between runs)."""


def study_settings(cfg: ManiSkillReproduce) -> ManiSkillStudySettings:
    """The study the flags ask for."""
    return ManiSkillStudySettings(
        out=cfg.out, envs=tuple(cfg.envs), policies=tuple(cfg.policies), seeds=cfg.seeds,
        num=cfg.num, test=cfg.test, val=cfg.val, seen_episodes=cfg.seen_episodes or None,
        curve_episodes=cfg.curve_episodes or None, curve_every=cfg.curve_every, paper_protocol=cfg.paper_protocol,
        jobs=cfg.jobs,
        control_mode=cfg.control_mode, horizon=cfg.horizon, procs=cfg.procs, backend=cfg.backend,
        action_noise=cfg.action_noise, hold_after_success=cfg.hold_after_success,
        train=TrainConfig(data=cfg.out / "<task>" / "demos" / "train.h5", iters=cfg.iters, device=cfg.device,
                          batch_size=cfg.batch_size, context=cfg.context, n_centres=cfg.n_centres,
                          use_actions=cfg.use_actions, keep_checkpoints=cfg.keep_checkpoints, compile=cfg.compile,
                          bf16=cfg.bf16, ignore_obs=tuple(cfg.ignore_obs), cot_weight=cfg.cot_weight,
                          offset_from=cfg.offset_from, obs_std_floor=cfg.obs_std_floor),
    )


def reproduce(cfg: ManiSkillReproduce) -> dict:
    """``cotpc reproduce maniskill``: run the study of the flags, print a summary."""
    settings = study_settings(cfg)
    check_study_flags("cotpc reproduce maniskill", settings.train, settings.policies,
                      {"--seeds": settings.seeds, "--jobs": settings.jobs, "--procs": settings.procs,
                       "--num": settings.num, "--curve-every": settings.curve_every}, env_ids=settings.envs)
    results = run(settings)
    print()
    print(f"{'task':<22}{'policy':<10}{'seen %':>10}{'unseen %':>10}   (success_once, mean over seeds)")
    for env_id, by_policy in results.items():
        if env_id != "meta":
            for name, r in by_policy.items():
                print(f"{env_id:<22}{name:<10}{r['seen']['mean']:>10.1f}{r['unseen']['mean']:>10.1f}")
    print(f"\nreport: {cfg.out / 'report.md'}")
    return results


SUITE = register_suite(Suite(
    name="maniskill", owns=is_maniskill_env, demos=ManiSkillDemos, make_demos=make_demos, evaluate=evaluate_run,
    reproduce=ManiSkillReproduce, run_study=reproduce,
))
