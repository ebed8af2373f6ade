"""Summarise a validation screen of maze runs against a reference, as in docs/results/maze.md.

    python scripts/screen-summary.py DIR [--reference REF_DIR | --reference-json NAME] [--policies cotpc bet]
        [--seeds 0 1 2 3 4 5] [--add NAME --how TEXT]

DIR holds P/seedS run directories, each scored with `cotpc eval DIR/P/seedS --split val --out
DIR/P/seedS/eval_val.json` (and, once the setting is chosen on validation, `--split unseen` into
eval_unseen.json). For each split scored, prints each policy's success per seed and mean +- std (ddof 0), the
paired difference between the first two policies, and each policy against the same seeds of the reference
(a run directory of the same layout, or a screen already stored in docs/results/maze-screens.json) +- its
standard error. ``--add NAME`` stores the runs in that JSON under NAME (``--how`` says what differs).
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
from pathlib import Path

SCREENS = Path(__file__).resolve().parent.parent / "docs" / "results" / "maze-screens.json"


def read_runs(root: Path, policies: list[str], seeds: list[int]) -> dict[str, dict]:
    runs = {}
    for p in policies:
        for s in seeds:
            run = root / p / f"seed{s}"
            scored = run / "eval_val.json"
            if not scored.is_file():
                continue
            entry = {"val": json.loads(scored.read_text())["summary"]["success_rate"]}
            unseen = run / "eval_unseen.json"  # scored on the test configs once the setting is chosen
            if unseen.is_file():
                entry["unseen"] = json.loads(unseen.read_text())["summary"]["success_rate"]
            val = json.loads((run / "config.json").read_text()).get("val") or {}
            if "last_action_err" in val:
                entry["last_action_err"] = val["last_action_err"]
            runs[f"{p}/seed{s}"] = entry
    return runs


def paired(a: dict[int, float], b: dict[int, float]) -> str:
    common = sorted(set(a) & set(b))
    if len(common) < 2:
        return "n/a"
    d = [a[s] - b[s] for s in common]
    return f"{statistics.mean(d):+.1f} +- {statistics.stdev(d) / math.sqrt(len(d)):.1f} ({len(d)} seeds)"


def per_seed(runs: dict[str, dict], policy: str, split: str = "val") -> dict[int, float]:
    return {int(k.split("seed")[1]): 100 * v[split] for k, v in runs.items()
            if k.split("/")[0] == policy and split in v}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dir", type=Path)
    ap.add_argument("--reference", type=Path, help="run directory of the reference screen")
    ap.add_argument("--reference-json", help="name of a screen in docs/results/maze-screens.json")
    ap.add_argument("--policies", nargs="+", default=["cotpc", "bet"])
    ap.add_argument("--seeds", nargs="+", type=int, default=list(range(12)))
    ap.add_argument("--add", help="store these runs in maze-screens.json under this name")
    ap.add_argument("--how", default="", help="what the screen changes (stored with --add)")
    args = ap.parse_args()

    runs = read_runs(args.dir, args.policies, args.seeds)
    if not runs:
        raise SystemExit(f"no scored runs (P/seedS/eval_val.json) under {args.dir}")
    ref = {}
    if args.reference:
        ref = read_runs(args.reference, args.policies, args.seeds)
    elif args.reference_json:
        ref = json.loads(SCREENS.read_text())["screens"][args.reference_json]["runs"]
    for split in ("val", "unseen"):
        if not any(split in v for v in runs.values()):
            continue
        print(f"{split}:")
        for p in args.policies:
            got = per_seed(runs, p, split)
            if not got:
                continue
            xs = list(got.values())
            line = (f"  {p}: {' / '.join(f'{v:.0f}' for v in xs)} -> {statistics.mean(xs):.1f} "
                    f"+- {statistics.pstdev(xs):.1f}")
            if ref:
                line += f"; minus reference {paired(got, per_seed(ref, p, split))}"
            print(line)
        if len(args.policies) >= 2:
            a, b = args.policies[:2]
            print(f"  {a} minus {b}: {paired(per_seed(runs, a, split), per_seed(runs, b, split))}")
    if args.add:
        data = json.loads(SCREENS.read_text())
        data["screens"][args.add] = {"runs_under": str(args.dir), "how": args.how, "runs": runs}
        SCREENS.write_text(json.dumps(data, indent=1) + "\n")
        print(f"stored under {args.add!r} in {SCREENS}")


if __name__ == "__main__":
    main()
