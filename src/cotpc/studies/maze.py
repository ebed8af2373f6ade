"""``cotpc reproduce maze``: demos -> subskills -> training of every policy and seed -> evaluation -> report.

Every step writes into ``OUT`` and is skipped when its output is already complete, so an interrupted run picks up
where it stopped (training resumes from its last checkpoint). Checkpoints are the final weights of a fixed
schedule; nothing is ever selected on evaluation success.
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

from cotpc.envs.maze.demos import MazeDemos, make_demos, write_splits
from cotpc.envs.maze.env import ENV_ID, HORIZON, PAPER_MIN_ACTION, RULES, SPEC
from cotpc.envs.maze.rollout import eval_name, evaluate, evaluate_run, load_split_configs
from cotpc.studies.suites import Suite, register_suite
from cotpc.studies.runs import (
    PROTOCOL_CHECKPOINTS, Evaluation, cpu_count, describe_hardware, fresh_eval, jsonable, plot_learning_curves,
    check_study_flags, policy_loader, provenance, stats, train_and_evaluate,
)
from cotpc.subskills.labeling import label_file
from cotpc.training.train import TrainConfig, resolve_device

# The paper's Table 1 (Moving Maze, unseen configs, success %). Its ablations (Table 4) are on ManiSkill2 only.
PAPER_UNSEEN = SPEC.paper_success
BASELINES = ("bc", "dt", "bet", "cotpc")
# Result key -> (split, deadly_gaps, min_action); the key is also the name of the run's eval_<key>.json. Training
# never sees these rules (the demos never step into a gap and their action components are all in [1.5, 4]), so the
# same checkpoints are evaluated under each: the paper's rules (the default: deadly gaps and actions in [1.5, 4];
# key = the split), and the forgiving readings of them kept for comparison (key = split_<rules>, MazeRules).
# "val" configs come from the validation seed range: they are for diagnosing and choosing settings, so that
# nothing is ever tuned on "unseen" (test) configs.
EVAL_KEYS = {
    eval_name(split, r.deadly_gaps, r.min_action): (split, r.deadly_gaps, r.min_action)
    for r, splits in (
        (RULES["paper"], ("seen", "val", "unseen")),
        (RULES["forgiving"], ("seen", "val", "unseen")),
        (RULES["any-action"], ("val", "unseen")),
        (RULES["safe-gaps"], ("val", "unseen")),
    )
    for split in splits
}
CURVE_KEYS = ("val", "val_forgiving")  # validation success of every kept checkpoint, under these rules
ABLATIONS = ("only-last", "only-next", "random", "vanilla", "o-shared", "swapped", "bet-prompt", "no-rand-mask", "decoupled")


@dataclass
class ReproduceSettings:
    out: Path
    seeds: int
    train: TrainConfig
    """What every run shares (schedule, batch, K, ...); its data is the study's demos/train.h5."""
    policies: tuple[str, ...]
    ablations: tuple[str, ...]
    beta: float
    cost: str = SPEC.defaults.cost
    train_demos: int = 400
    test_demos: int = 100
    val_demos: int = 100
    demo_seed: int = 0
    workers: int = 2
    jobs: int = 1


def run(s: ReproduceSettings) -> dict:
    t_start = time.perf_counter()
    out = Path(s.out)
    demos = out / "demos"
    # 1. demos (only the missing splits are generated; each split has its own seed range, so this is the same
    # as generating them all at once)
    missing = {split: n for split, n in (("train", s.train_demos), ("val", s.val_demos), ("test", s.test_demos))
               if not (demos / f"{split}.h5").exists()}
    if missing:
        print(f"[1/5] demos ({', '.join(missing)}) -> {demos}", flush=True)
        write_splits(demos, missing.get("train", 0), missing.get("test", 0), val=missing.get("val", 0),
                     seed=s.demo_seed, workers=s.workers)
    # 2. unsupervised subskills on the training demos (cheap: always re-labelled with this beta)
    print(f"[2/5] subskill discovery, {s.cost} cost, beta={s.beta}", flush=True)
    seg, _ = label_file(demos / "train.h5", beta=s.beta, min_size=1, cost=s.cost)
    # 3. training, 4. evaluation (an evaluation already on disk for the same weights and configs is reused)
    split_seeds = {split: load_split_configs(demos, split)[1] for split in {split for split, *_ in EVAL_KEYS.values()}}
    results: dict = {}
    names = list(s.policies) + [a for a in s.ablations if a not in s.policies]
    # ablations: one seed each
    runs = [(name, seed) for name in names for seed in (range(s.seeds) if name in s.policies else range(1))]
    template = dataclasses.replace(s.train, data=demos / "train.h5")
    eval_device = resolve_device(template.device)
    evaluations = {key: Evaluation(cached=functools.partial(_cached_eval, key=key, seeds=split_seeds[split]),
                                   evaluate=functools.partial(_evaluate_run, key=key, demos=demos,
                                                              videos=out / "videos"))
                   for key, (split, *_) in EVAL_KEYS.items()}
    curves: dict = {}
    protocol: dict = {name: {} for name in names}  # the paper's protocol, with --keep-checkpoints
    selected: dict = {name: {} for name in names}  # our headline with validation-selected weights, likewise

    def after_run(name: str, seed: int, run_dir: Path, summaries: dict) -> None:
        if template.keep_checkpoints:
            curves[f"{name}/seed{seed}"] = checkpoint_curve(run_dir, demos, split_seeds["val"], eval_device)
            selected[name][f"seed{seed}"] = validation_selected(run_dir, curves[f"{name}/seed{seed}"], demos,
                                                                split_seeds["unseen"], eval_device)
            protocol[name][f"seed{seed}"] = last_checkpoints_success(run_dir, demos, split_seeds["unseen"],
                                                                     eval_device)
        rate = {key: 100 * summaries[key]["success_rate"] for key in summaries}
        print(
            f"[4/5] {name} seed {seed}: seen {rate['seen']:.1f}%  val {rate['val']:.1f}%  "
            f"unseen {rate['unseen']:.1f}%  (forgiving rules: seen "
            f"{rate['seen_forgiving']:.1f}%  val {rate['val_forgiving']:.1f}%  "
            f"unseen {rate['unseen_forgiving']:.1f}%)",
            flush=True,
        )

    grid = train_and_evaluate(out, template, runs, evaluations,
                              jobs=s.jobs, device=eval_device, step="[3/5]", after_run=after_run)
    timings = grid.train_seconds
    for name in names:
        per_key = grid.summaries[name]
        results[name] = {}
        for key in EVAL_KEYS:
            raised = [x["raised_share"] for x in per_key[key] if "raised_share" in x]  # action components raised
            results[name][key] = {**stats([100 * x["success_rate"] for x in per_key[key]]),
                                  "region_transitions": float(np.mean([x["mean_region_transitions"]
                                                                       for x in per_key[key]])),
                                  **({"raised_share": float(np.mean(raised))} if raised else {})}
        if selected[name]:
            results[name]["val_selected"] = {
                **stats([r["unseen"] for r in selected[name].values()]),
                "rule": "per run, the kept checkpoint with the highest validation success under the paper's rules "
                        "(the later one on a tie); its success on the unseen (test) configs: selected on validation",
                "runs": selected[name],
            }
        if protocol[name]:
            results[name]["paper_protocol"] = {
                "best": max(max(r["unseen"]) for r in protocol[name].values()),
                "rule": f"best over {len(protocol[name])} run(s) x the last {PROTOCOL_CHECKPOINTS} kept checkpoints, "
                        "success on the unseen (test) configs under the paper's rules: selected on the test configs",
                "runs": protocol[name],
            }
    results["meta"] = {
        **provenance(),
        "settings": jsonable(dataclasses.replace(s, train=template)),
        "ablations": [a for a in s.ablations if a not in s.policies],
        "subskills": seg,
        "wall_seconds": round(time.perf_counter() - t_start, 1),  # this invocation (finished runs are reused)
        "train_seconds_total": round(sum(t for t in timings.values() if t), 1),
        "train_seconds": timings,
        "horizon": HORIZON,
        "success_unit": "percent of episodes",
        "checkpoint_selection": "final weights of a fixed schedule (no selection on evaluation success)",
    }
    if curves:
        results["meta"]["val_success_by_iteration"] = curves
    (out / "results.json").write_text(json.dumps(results, indent=1))
    print("[5/5] report", flush=True)
    write_report(results, out)
    return results


def checkpoint_curve(run_dir: Path, demos: Path, val_seeds: list[int], device: str) -> dict:
    """Success on the validation configs (the paper's rules, and the forgiving ones) of every checkpoint kept
    under ``run_dir/checkpoints``: how success moves with training length, measured without the test configs.
    Cached like the final evaluations."""
    keys = CURVE_KEYS
    curve: dict = {"iteration": [], **{key: [] for key in keys}}
    for ckpt in sorted((run_dir / "checkpoints").glob("step_*")):
        curve["iteration"].append(int(ckpt.name.split("_")[1]))
        load = policy_loader(ckpt, device)
        for key in keys:
            summary = _evaluate_cached(ckpt, key, demos, val_seeds, load)
            curve[key].append(100 * summary["success_rate"])
    return curve


def validation_selected(run_dir: Path, curve: dict, demos: Path, test_seeds: list[int], device: str) -> dict:
    """Our headline with checkpoint selection: of the checkpoints kept under ``run_dir/checkpoints`` (``curve``,
    from :func:`checkpoint_curve`), the one with the highest success on the validation configs under the paper's
    rules (the later one on a tie), and its success on the unseen configs. Only validation configs choose."""
    val = curve["val"]
    best = max(range(len(val)), key=lambda i: (val[i], i))
    ckpt = run_dir / "checkpoints" / f"step_{curve['iteration'][best]:07d}"
    unseen = _evaluate_cached(ckpt, "unseen", demos, test_seeds, policy_loader(ckpt, device))["success_rate"]
    return {"iteration": curve["iteration"][best], "val": val[best], "unseen": 100 * unseen}


def last_checkpoints_success(run_dir: Path, demos: Path, test_seeds: list[int], device: str) -> dict:
    """Success on the unseen (test) configs, under the paper's rules, of each of the last
    :data:`PROTOCOL_CHECKPOINTS` checkpoints kept under ``run_dir/checkpoints``: the raw material of the paper's
    protocol (best of 3 runs over the last 20 checkpoints, as Diffusion Policy's), which selects on the test
    configs. Reported beside our headline, labelled, never as it. Cached like the final evaluations."""
    kept = sorted((run_dir / "checkpoints").glob("step_*"))[-PROTOCOL_CHECKPOINTS:]
    out: dict = {"iteration": [], "unseen": []}
    for ckpt in kept:
        out["iteration"].append(int(ckpt.name.split("_")[1]))
        out["unseen"].append(100 * _evaluate_cached(ckpt, "unseen", demos, test_seeds, policy_loader(ckpt, device))[
            "success_rate"])
    return out


def _evaluate_cached(run_dir: Path, key: str, demos: Path, seeds: list[int], load,
                     video_dir: Path | None = None) -> dict:
    """The summary of ``run_dir/eval_<key>.json`` (split and rules from ``EVAL_KEYS[key]``): reused when it is fresh
    for these weights, configs and rules, else evaluated (with ``load()``'s policy) and written."""
    summary = _cached_eval(run_dir, key, seeds)
    return summary if summary is not None else _evaluate_key(run_dir, key, demos, load, video_dir)


def _evaluate_key(run_dir: Path, key: str, demos: Path, load, video_dir: Path | None = None) -> dict:
    """Evaluate ``load()``'s policy on the split and rules of ``EVAL_KEYS[key]``; write ``run_dir/eval_<key>.json``."""
    split, deadly, min_action = EVAL_KEYS[key]
    r = evaluate(load(), demos, split, video_dir=video_dir, num_videos=2, deadly_gaps=deadly, min_action=min_action)
    r.to_json(run_dir / f"eval_{key}.json")
    return r.summary()


def _evaluate_run(run_dir: Path, load, key: str, demos: Path, videos: Path) -> dict:
    """:func:`_evaluate_key` of a study's run, with videos of seed 0's unseen rollouts in ``videos/<policy>/``."""
    video_dir = videos / run_dir.parent.name if (key == "unseen" and run_dir.name == "seed0") else None
    return _evaluate_key(run_dir, key, demos, load, video_dir)


def _cached_eval(run_dir: Path, key: str, seeds: list[int]) -> dict | None:
    """The summary of ``eval_<key>.json`` if it was written after the current weights, for exactly these
    configuration seeds and the rules of ``EVAL_KEYS[key]``; else None (evaluate again)."""
    _, deadly, min_action = EVAL_KEYS[key]
    saved = fresh_eval(run_dir, f"eval_{key}.json")
    try:
        same = ([e["seed"] for e in saved["episodes"]] == list(seeds) and saved["summary"]["deadly_gaps"] == deadly
                and saved["summary"].get("min_action", 0.0) == min_action)  # files from before the rule: 0
    except (KeyError, TypeError):
        return None
    return saved["summary"] if same else None


def write_report(results: dict, out: Path) -> Path:
    """``report.md`` with the results tables, learning curves and success bars."""
    meta = results["meta"]
    s = meta["settings"]
    policies = [p for p in results if p != "meta" and p not in meta["ablations"]]
    lines = [
        "# Moving Maze results",
        "",
        f"Command: `{meta.get('command') or 'cotpc reproduce maze'}`  ",
        f"{s['train_demos']} training demos (seen configs), {s.get('val_demos', 0)} validation configs, "
        f"{s['test_demos']} test demos (unseen configs), "
        f"subskills: {s['cost']} cost, beta {s['beta']}, {s['train']['iters']} training iterations per run at batch "
        f"{s['train']['batch_size'] or 'default (256; bc 32)'}, "
        f"{s['train']['n_centres'] or f'default ({SPEC.defaults.n_centres})'} k-means centres, {s['seeds']} seed(s) per policy, "
        f"horizon {meta['horizon']}"
        + (f"; CoT weight {s['train']['cot_weight']}" if s["train"].get("cot_weight") is not None else "")
        + (f"; offset head on the {s['train']['offset_from']} token" if s["train"].get("offset_from") else "")
        + ".  ",
        f"Checkpoints: {meta['checkpoint_selection']}.  ",
        f"Training {meta.get('train_seconds_total', 0) / 60:.1f} min in all, this invocation "
        f"{meta['wall_seconds'] / 60:.1f} min, on {describe_hardware(meta['hardware'])}; torch "
        f"{meta['versions']['torch']}, numpy {meta['versions']['numpy']}.",
        "",
        f"Success rate (%): mean ± std over seeds, best seed in brackets; region transitions: mean of 5. "
        f"The paper's rules (the default): a step into a gap ends the episode as a failure, and every action "
        f"component's magnitude is raised to at least {PAPER_MIN_ACTION:g} (\"both components in "
        f"[{PAPER_MIN_ACTION:g}, 4]\"); *raised*: the share of the policy's action components (unseen configs) "
        f"that were smaller and so were raised, mean over seeds (docs/moving-maze.md).",
        "",
        "| policy | seen | val | unseen | unseen transitions | raised | paper unseen |",
        "|---|---|---|---|---|---|---|",
    ]

    def cell(r):
        return f"{r['mean']:.1f} ± {r['std']:.1f} [{r['best']:.1f}]"

    for p in policies:
        r = results[p]
        lines.append(
            f"| {p} | {cell(r['seen'])} | {cell(r['val'])} | {cell(r['unseen'])} | "
            f"{r['unseen']['region_transitions']:.2f} | {100 * r['unseen'].get('raised_share', float('nan')):.1f}% | "
            f"{PAPER_UNSEEN.get(p, '–')} |"
        )
    with_selection = [p for p in policies if "val_selected" in results[p]]
    if with_selection:
        lines += [
            "",
            "**Validation-selected weights** (our headline with checkpoint selection, `--keep-checkpoints`): per run, "
            "the kept checkpoint with the highest success on the validation configs (paper's rules), scored on the "
            "unseen configs. Nothing is chosen on the unseen configs.",
            "",
            "| policy | unseen, final weights | unseen, validation-selected | selected iterations | paper unseen |",
            "|---|---|---|---|---|",
        ]
        for p in with_selection:
            vs = results[p]["val_selected"]
            its = ", ".join(str(r["iteration"]) for r in vs["runs"].values())
            lines.append(f"| {p} | {cell(results[p]['unseen'])} | {cell(vs)} | {its} | {PAPER_UNSEEN.get(p, '–')} |")
    with_protocol = [p for p in policies if "paper_protocol" in results[p]]
    if with_protocol:
        lines += [
            "",
            f"**The paper's protocol** (its ManiSkill2 tables: the best of 3 runs over the last "
            f"{PROTOCOL_CHECKPOINTS} checkpoints), unseen configs, the paper's rules. It selects on the test configs, "
            "so it is optimistic: shown to compare with the paper's numbers, never as our result.",
            "",
            "| policy | ours: final weights, mean ± std | paper's protocol: best of runs x checkpoints | checkpoints "
            "| paper unseen |",
            "|---|---|---|---|---|",
        ]
        for p in with_protocol:
            pp = results[p]["paper_protocol"]
            n = sum(len(r["unseen"]) for r in pp["runs"].values())
            lines.append(f"| {p} | {results[p]['unseen']['mean']:.1f} ± {results[p]['unseen']['std']:.1f} | "
                         f"{pp['best']:.1f} | {len(pp['runs'])} x {n // max(len(pp['runs']), 1)} | "
                         f"{PAPER_UNSEEN.get(p, '–')} |")
    lines += [
        "",
        "**Forgiving readings of the rules**, same checkpoints (`cotpc eval RUN --rules NAME`): *forgiving*, a step "
        "into a gap is blocked and any action up to 4 is allowed (this project's default before 2026-12); "
        "*any-action*, deadly gaps with any action; *safe-gaps*, blocked gaps with actions in "
        f"[{PAPER_MIN_ACTION:g}, 4].",
        "",
        "| policy | seen, forgiving | val, forgiving | unseen, forgiving | val, any-action | unseen, any-action "
        "| val, safe-gaps | unseen, safe-gaps |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for p in policies:
        r = results[p]
        lines.append(f"| {p} | " + " | ".join(cell(r[k]) for k in (
            "seen_forgiving", "val_forgiving", "unseen_forgiving", "val_any-action", "unseen_any-action",
            "val_safe-gaps", "unseen_safe-gaps")) + " |")
    if meta["ablations"]:
        lines += ["", "## CoTPC ablations (paper Table 4 presets, one seed each)", "",
                  "| preset | seen | val | unseen | seen, forgiving | val, forgiving | unseen, forgiving |",
                  "|---|---|---|---|---|---|---|"]
        for a in ["cotpc"] * ("cotpc" in results) + list(meta["ablations"]):
            r = results[a]
            name = f"{a} (full method, seed 0)" if a == "cotpc" else a
            first = {k: r[k]["runs"][0] for k in EVAL_KEYS}  # seed 0 of the full method, to compare like with like
            lines.append(f"| {name} | " + " | ".join(f"{first[k]:.1f}" for k in (
                "seen", "val", "unseen", "seen_forgiving", "val_forgiving", "unseen_forgiving")) + " |")
    figures = _plots(results, out, policies + list(meta["ablations"]))
    lines += ["", "## Figures", ""] + [f"![{f.stem}]({f.name})" for f in figures]
    videos = sorted((out / "videos").glob("*/*.gif")) if (out / "videos").exists() else []
    if videos:
        lines += ["", "Videos of unseen rollouts (seed 0 of each policy): " + ", ".join(
            f"[{v.parent.name}/{v.name}](videos/{v.parent.name}/{v.name})" for v in videos)]
    path = out / "report.md"
    path.write_text("\n".join(lines) + "\n")
    return path


def _plots(results: dict, out: Path, names: list[str]) -> list[Path]:
    import matplotlib  # heavy (about 1 s): imported only when a figure is drawn

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # after use("Agg"): no display needed

    paths = []
    # Success bars
    fig, ax = plt.subplots(figsize=(1.5 + 1.1 * len(names), 3.4))
    x = np.arange(len(names))
    keys = ["seen", "val", "unseen", "val_forgiving", "unseen_forgiving"]
    width = 0.8 / len(keys)
    for k, key in enumerate(keys):
        means = [results[n][key]["mean"] for n in names]
        stds = [results[n][key]["std"] for n in names]
        ax.bar(x + (k - (len(keys) - 1) / 2) * width, means, width, yerr=stds, label=key.replace("_", " "),
               capsize=2)
    ax.set_xticks(x, names, rotation=30, ha="right", fontsize=8)
    ax.set_ylabel("success rate (%)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    paths.append(out / "success.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)
    paths.append(plot_learning_curves(out / "runs", names, out / "learning_curves.png"))
    curves = results["meta"].get("val_success_by_iteration")
    if curves:
        paths.append(plot_val_success(curves, names, out / "val_success.png"))
    return paths


def plot_val_success(curves: dict, names: list[str], path: Path) -> Path:
    """Validation success against training iterations, one panel per rule, one line per run."""
    import matplotlib  # heavy (about 1 s): imported only when a figure is drawn

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # after use("Agg"): no display needed

    keys = [k for k in CURVE_KEYS if all(k in c for c in curves.values())]
    fig, axes = plt.subplots(1, len(keys), figsize=(4.5 * len(keys), 3.4), sharey=True, squeeze=False)
    axes = axes[0]
    colours = {n: f"C{i % 10}" for i, n in enumerate(names)}
    for ax, key in zip(axes, keys):
        for run, c in curves.items():
            name, seed = run.rsplit("/seed", 1)
            if name in colours and c["iteration"]:
                ax.plot(c["iteration"], c[key], color=colours[name], alpha=0.9 if seed == "0" else 0.45,
                        label=name if seed == "0" else None, marker=".")
        ax.set_title(key.replace("_", " "), fontsize=9)
        ax.set_xlabel("iteration")
    axes[0].set_ylabel("validation success (%)")
    axes[-1].legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path




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
    offset_from: Optional[Literal["state", "cot", "action"]] = None
    """The token the offset head of the k-means-headed policies reads (`cotpc train --offset-from`; default: the
    presets', the i-th CoT token for CoTPC as the paper, the state token for BeT)."""
    use_actions: Optional[bool] = None
    """Feed past actions to the transformer policies (default: the presets', True, as the paper); False
    conditions them on the states alone (`cotpc train --use-actions`; docs/results/maze.md, states only)."""
    grad_clip: Optional[float] = None
    """Clip the global gradient norm of every run to this value (default: off, as the paper)."""
    compile: Literal["off", "default", "reduce-overhead"] = "off"
    """torch.compile every training run (`cotpc train --compile`; reduce-overhead = CUDA graphs, for a GPU)."""
    bf16: Optional[bool] = None
    """bf16 autocast for every run (`cotpc train --bf16`; default: each run times its own step in both precisions
    and picks the faster, which on a busy machine can differ between runs)."""


def study_settings(cfg: MazeReproduce) -> ReproduceSettings:
    """The study the flags ask for: --quick and the task's defaults resolved."""
    quick = QUICK if cfg.quick else {}
    return ReproduceSettings(
        out=cfg.out,
        seeds=quick.get("seeds", cfg.seeds),
        policies=tuple(cfg.policies or quick.get("policies", BASELINES)),
        ablations=tuple(cfg.ablations if cfg.ablations is not None else quick.get("ablations", ABLATIONS)),
        beta=cfg.beta if cfg.beta is not None else SPEC.defaults.beta,
        cost=cfg.cost or SPEC.defaults.cost,
        train_demos=cfg.train_demos,
        test_demos=cfg.test_demos,
        val_demos=cfg.val_demos,
        workers=cfg.workers,
        jobs=cfg.jobs,
        train=TrainConfig(
            data=cfg.out / "demos" / "train.h5", device=cfg.device,
            iters=cfg.iters if cfg.iters is not None else quick.get("iters", FULL_ITERS),
            batch_size=cfg.batch_size if cfg.batch_size is not None else quick.get("batch_size"),
            n_centres=cfg.n_centres if cfg.n_centres is not None else quick.get("n_centres"),
            keep_checkpoints=cfg.keep_checkpoints, cot_weight=cfg.cot_weight, compile=cfg.compile, bf16=cfg.bf16,
            use_actions=cfg.use_actions, offset_from=cfg.offset_from,
            **({"grad_clip": cfg.grad_clip} if cfg.grad_clip is not None else {})),
    )


def reproduce(cfg: MazeReproduce) -> dict:
    """``cotpc reproduce maze``: resolve the flags (--quick, the task's defaults), run the study, print a summary."""
    settings = study_settings(cfg)
    check_study_flags("cotpc reproduce maze", settings.train, settings.policies + settings.ablations,
                      {"--seeds": settings.seeds, "--jobs": settings.jobs, "--workers": settings.workers,
                       "--train-demos": settings.train_demos}, env_ids=(ENV_ID,))
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
    return results


def _subskill_plots(plot_dir: Path, episodes: list, ends: list, titles: list) -> list[Path]:
    from cotpc.envs.maze.figure import plot_maze_paths  # imports matplotlib (heavy): only when plotting

    return [plot_maze_paths(plot_dir / "subskills_maze_paths.png", episodes, ends, titles)]


SUITE = register_suite(Suite(
    name="maze", owns=lambda env_id: env_id == ENV_ID, demos=MazeDemos, make_demos=make_demos,
    evaluate=evaluate_run, reproduce=MazeReproduce, run_study=reproduce, subskill_plots=_subskill_plots,
))
