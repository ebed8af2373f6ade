"""``cotpc segment``: discover subskills in a trajectory file and store them as ``traj_<i>/subskill_ends``."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import tyro

from cotpc.data import load_trajectories
from cotpc.envs.spec import task_defaults
from cotpc.subskills.evaluate import sweep, sweep_table
from cotpc.subskills.labeling import label_file, label_file_from_key_steps

Cost = Literal["mean-cosine", "sum-cosine"]


@dataclass
class Config:
    """Discover subskills (exact minimiser of the paper's segmentation objective) for every demo of DATA and store
    them in the file as traj_<i>/subskill_ends (with beta, min_size, method and cost as attributes); re-running
    replaces them. With --sweep-beta nothing is written: the key-step recovery table is printed instead."""

    data: tyro.conf.Positional[Path]
    """Trajectory file (NAME.h5, with NAME.json beside it)."""
    beta: float | None = None
    """Penalty per subskill. Default: the task's (cotpc.envs.spec.task_defaults, from the data's env id), or the
    paper's single-arm 0.05 for data of an unregistered environment."""
    cost: Cost | None = None
    """Segment cost: 'mean-cosine' is the paper's (mean cosine distance to the segment mean); 'sum-cosine' is n
    times that. Default: the task's, or 'mean-cosine' for data of an unregistered environment."""
    min_size: int = 1
    """Minimum number of actions per subskill."""
    plot: Path | None = None
    """Directory for figures: action similarity maps with boundaries, the task suite's own figures (for example
    the demo paths coloured by subskill) and, with --sweep-beta, precision/recall against beta."""
    num_plot: int = 4
    """Demos shown per figure (the first ones of the file)."""
    sweep_beta: tuple[float, ...] = ()
    """Evaluate these betas instead of labelling: subskills per demo and, for demos with privileged key_steps,
    precision/recall within --tol steps. Prints a markdown table per cost in --sweep-cost."""
    sweep_cost: tuple[Cost, ...] = ("mean-cosine", "sum-cosine")
    """Costs evaluated by --sweep-beta."""
    tol: int = 2
    """Tolerance in steps when matching discovered boundaries to key_steps."""
    json: bool = False
    """Print the summary (or the sweep rows) as JSON."""
    privileged: bool = False
    """Do not discover: store each demo's privileged key_steps (recorded by a demonstrator) as its subskill
    boundaries, like the official code's simulator key states. For comparing against discovery."""


def defaults_for(env_id: str | None, beta: float | None, cost: str | None) -> tuple[float, str]:
    """Fill unset beta / cost with the task's defaults (cotpc.envs.task_defaults)."""
    defaults = task_defaults(env_id)
    return (defaults.beta if beta is None else beta), (defaults.cost if cost is None else cost)


def format_summary(path: Path, s: dict) -> str:
    lines = [
        (f"labelled {s['demos']} demos of {path} with their privileged key_steps" if s["method"] == "key-steps" else
         f"labelled {s['demos']} demos of {path} (cost={s['cost']}, beta={s['beta']:g}, min_size={s['min_size']}, "
         f"{s['method']}) in {s['seconds']:.3f} s"),
        f"subskills per demo: mean {s['subskills_mean']:.2f}, min {s['subskills_min']}, max {s['subskills_max']}",
        f"segment length (actions): mean {s['length_mean']:.1f}, min {s['length_min']}, max {s['length_max']}",
    ]
    if "precision" in s:
        lines.append(
            f"privileged key_steps within +-{s['tol']} steps: precision {s['precision']:.3f}, "
            f"recall {s['recall']:.3f}, "
            f"F1 {s['f1']:.3f} ({s['matched']} matched; {s['predicted']} discovered, {s['true']} true boundaries)"
        )
    if "recall_per_key" in s:
        lines.append("  found per key step (demos with a discovered boundary within tolerance): "
                     + ", ".join(f"{x:.2f}" for x in s["recall_per_key"]))
    lines.append("stored traj_<i>/subskill_ends (attributes: beta, min_size, method, cost)")
    return "\n".join(lines)


def run(cfg: Config) -> dict:
    if cfg.min_size < 1:
        raise SystemExit(f"--min-size must be >= 1, got {cfg.min_size}")
    ts = load_trajectories(cfg.data)
    env_id = ts.env_info.get("env_id")
    episodes = ts.episodes
    keys = [ep.extras["key_steps"] for ep in episodes] if all("key_steps" in ep.extras for ep in episodes) else None
    actions = [ep.actions for ep in episodes]

    if cfg.sweep_beta:
        tables = {c: sweep(actions, keys, cfg.sweep_beta, cfg.min_size, cfg.tol, c) for c in cfg.sweep_cost}
        if cfg.json:
            print(json.dumps(tables, indent=1))
        else:
            for c, rows in tables.items():
                print(f"\n{c}: {len(episodes)} demos of {cfg.data}, min_size={cfg.min_size}"
                      + (f", key_steps within +-{cfg.tol} steps" if keys is not None else ""))
                print(sweep_table(rows))
        if cfg.plot is not None:
            from cotpc.subskills.plots import plot_sweep  # matplotlib (heavy): only with --plot

            print(f"wrote {plot_sweep(cfg.plot / 'subskills_sweep.png', tables, cfg.tol)}")
        return {"sweep": tables}

    if cfg.privileged:
        summary, ends = label_file_from_key_steps(cfg.data, trajectories=ts)
    else:
        beta, cost = defaults_for(env_id, cfg.beta, cfg.cost)
        summary, ends = label_file(cfg.data, beta, cfg.min_size, cost, cfg.tol, trajectories=ts)
    print(json.dumps(summary, indent=1) if cfg.json else format_summary(cfg.data, summary))
    if cfg.plot is not None:
        # only with --plot: matplotlib, and the task suites (every study, the training stack) are heavy imports
        from cotpc.studies.suites import suite_for_env
        from cotpc.subskills.plots import plot_similarity_maps

        k = min(cfg.num_plot, len(episodes))
        titles = [f"traj_{ep.episode_id}: {len(e)} subskills" for ep, e in zip(episodes[:k], ends[:k])]
        files = [plot_similarity_maps(cfg.plot / "subskills_similarity.png", actions[:k], ends[:k], titles,
                                      keys[:k] if keys is not None else None)]
        suite = suite_for_env(env_id)
        if suite is not None and suite.subskill_plots is not None:  # the task's own figures (maze: the paths)
            files += suite.subskill_plots(cfg.plot, episodes[:k], ends[:k], titles)
        for f in files:
            print(f"wrote {f}")
    return summary


def main(argv: list[str], prog: str = "cotpc segment") -> None:
    cfg = tyro.cli(Config, args=argv, prog=prog)
    try:
        run(cfg)
    except ValueError as e:  # bad file (TrajectoryFormatError) or parameters: a message, not a traceback
        raise SystemExit(f"{prog}: {e}") from None
