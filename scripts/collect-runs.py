"""Collect the evaluation summaries of ManiSkill runs into one JSON, as docs/results/maniskill-dart-ctx60.json.

    python scripts/collect-runs.py ROOT --runs P/seedS ... --out JSON --setting TEXT [--commands TEXT]
        [--extra NAME=RUN_DIR ...] [--plot PNG]

For each ``ROOT/P/seedS`` run it reads what `cotpc eval` and `scripts/ms-trace.py` wrote there: the validation
curve (``checkpoints/step_N/eval_val.json`` of every kept checkpoint that was scored, and the final weights'
``eval_val.json`` under the run's last iteration), ``eval_unseen.json``, ``eval_seen.json`` and
``trace_val.json`` (and ``trace_val_*.json``, traces under inference-time probes such as ``--zero-obs``, under
``other_traces``), and the unseen scores of kept checkpoints (``checkpoints/step_N/eval_unseen.json``, the
weights chosen on the validation curve); whatever is missing is left out (a run still training, a split not yet scored). Any other
``eval_*.json`` of the run or its checkpoints (an evaluation with other inference settings, written with
``cotpc eval --out``, e.g. ``--action-horizon 1``) goes under ``other_evals``, keyed by its path in the run
(the settings are in its summary). ``--extra``
adds the trace of another run directory under NAME (a diagnosis run with another schedule). ``--plot`` draws
the validation curves (success_once against training samples seen) into a PNG. Only the
``summary`` block of each file is kept; the per-episode records stay in the run directories.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def summary(path: Path) -> dict | None:
    return json.loads(path.read_text())["summary"] if path.is_file() else None


def collect_run(run: Path) -> dict:
    row: dict = {}
    curve, unseen_by_checkpoint = {}, {}
    for ckpt in sorted(p for p in (run / "checkpoints").glob("step_*") if p.is_dir()):  # not logs beside them
        step = str(int(ckpt.name.split("_")[1]))
        scored = summary(ckpt / "eval_val.json")
        if scored is not None:
            curve[step] = scored
        scored = summary(ckpt / "eval_unseen.json")
        if scored is not None:
            unseen_by_checkpoint[step] = scored
    final = summary(run / "eval_val.json")
    if final is not None:
        saved_at = json.loads((run / "config.json").read_text()).get("step")  # the iteration of the final weights
        curve[str(saved_at) if saved_at is not None else "final"] = final
    if curve:
        row["val_curve_50_episodes"] = curve
    for split in ("unseen", "seen"):
        scored = summary(run / f"eval_{split}.json")
        if scored is not None:
            row[split] = scored
    if unseen_by_checkpoint:
        row["unseen_by_checkpoint"] = unseen_by_checkpoint
    standard = {"eval_val.json", "eval_unseen.json", "eval_seen.json"}
    others = {str(path.relative_to(run)): summary(path) for path in sorted(run.glob("**/eval_*.json"))
              if path.name not in standard}
    if others:
        row["other_evals"] = others
    trace = summary(run / "trace_val.json")
    if trace is not None:
        row["trace_val"] = trace
    probes = {f.stem: summary(f) for f in sorted(run.glob("trace_val_*.json"))}  # ms-trace with inference probes
    if probes:
        row["other_traces"] = probes
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("root", type=Path, help="directory holding P/seedS run directories")
    parser.add_argument("--runs", nargs="+", required=True, help="P/seedS names under ROOT")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--setting", required=True, help="what the runs are (demos, schedule, seeds)")
    parser.add_argument("--commands", default="", help="where the commands that made the runs are written")
    parser.add_argument("--extra", nargs="*", default=[], help="NAME=RUN_DIR: the trace of another run")
    parser.add_argument("--plot", type=Path, help="PNG: validation success_once against training samples seen")
    args = parser.parse_args()
    out = {"setting": args.setting, "commands": args.commands, "runs": {}}
    for name in args.runs:
        run = args.root / name
        if not run.is_dir():
            raise SystemExit(f"no run directory {run}")
        out["runs"][name] = collect_run(run)
    for item in args.extra:
        name, _, run = item.partition("=")
        if not run:
            raise SystemExit(f"--extra takes NAME=RUN_DIR, got {item!r}")
        out["runs"][name] = {"trace_val": summary(Path(run) / "trace_val.json")}
    args.out.write_text(json.dumps(out, indent=1) + "\n")
    print(f"wrote {args.out} ({len(out['runs'])} runs)")
    if args.plot:
        print(f"wrote {plot_curves(args.root, out['runs'], args.plot)}")


def plot_curves(root: Path, runs: dict, path: Path) -> Path:
    """The validation curves of the runs that have one, in percent against samples (iterations x batch size)."""
    from cotpc.studies.maniskill import plot_val_curves  # matplotlib only when a figure is asked for

    curves = {}
    for name, row in runs.items():
        points = {k: v for k, v in row.get("val_curve_50_episodes", {}).items() if k.isdigit()}
        if not points:
            continue
        batch = json.loads((root / name / "config.json").read_text())["policy"]["batch_size"]
        steps = sorted(points, key=int)
        curves[name] = {"samples": [int(k) * batch for k in steps],
                        "success_once": [100 * points[k]["success_once"] for k in steps]}
    if not curves:
        raise SystemExit("--plot: none of the runs has a scored validation checkpoint")
    path.parent.mkdir(parents=True, exist_ok=True)
    return plot_val_curves(curves, path)


if __name__ == "__main__":
    main()
