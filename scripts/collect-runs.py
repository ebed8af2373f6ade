"""Collect the evaluation summaries of ManiSkill runs into one JSON, as docs/results/maniskill-dart-ctx60.json.

    python scripts/collect-runs.py ROOT --runs P/seedS ... --out JSON --setting TEXT [--commands TEXT]
        [--extra NAME=RUN_DIR ...]

For each ``ROOT/P/seedS`` run it reads what `cotpc eval` and `scripts/ms-trace.py` wrote there: the validation
curve (``checkpoints/step_N/eval_val.json`` of every kept checkpoint that was scored, and the final weights'
``eval_val.json`` under the run's last iteration), ``eval_unseen.json``, ``eval_seen.json`` and
``trace_val.json``; whatever is missing is left out (a run still training, a split not yet scored). Any other
``eval_*.json`` of the run or its checkpoints (an evaluation with other inference settings, written with
``cotpc eval --out``, e.g. ``--action-horizon 1``) goes under ``other_evals``, keyed by its path in the run
(the settings are in its summary). ``--extra``
adds the trace of another run directory under NAME (a diagnosis run with another schedule). Only the
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
    curve = {}
    for ckpt in sorted((run / "checkpoints").glob("step_*")):
        scored = summary(ckpt / "eval_val.json")
        if scored is not None:
            curve[str(int(ckpt.name.split("_")[1]))] = scored
    final = summary(run / "eval_val.json")
    if final is not None:
        step = json.loads((run / "config.json").read_text()).get("step")  # the iteration the weights were saved at
        curve[str(step) if step is not None else "final"] = final
    if curve:
        row["val_curve_50_episodes"] = curve
    for split in ("unseen", "seen"):
        scored = summary(run / f"eval_{split}.json")
        if scored is not None:
            row[split] = scored
    standard = {"eval_val.json", "eval_unseen.json", "eval_seen.json"}
    others = {str(path.relative_to(run)): summary(path) for path in sorted(run.glob("**/eval_*.json"))
              if path.name not in standard}
    if others:
        row["other_evals"] = others
    trace = summary(run / "trace_val.json")
    if trace is not None:
        row["trace_val"] = trace
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("root", type=Path, help="directory holding P/seedS run directories")
    parser.add_argument("--runs", nargs="+", required=True, help="P/seedS names under ROOT")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--setting", required=True, help="what the runs are (demos, schedule, seeds)")
    parser.add_argument("--commands", default="", help="where the commands that made the runs are written")
    parser.add_argument("--extra", nargs="*", default=[], help="NAME=RUN_DIR: the trace of another run")
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


if __name__ == "__main__":
    main()
