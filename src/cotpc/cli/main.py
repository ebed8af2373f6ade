"""The ``cotpc`` command: one verb per module, each parsing its own flags with tyro.

Verbs are imported lazily so ``cotpc demos`` does not pay for importing the training stack.
"""

from __future__ import annotations

import importlib
import sys

from cotpc import __version__

# verb -> (module with a ``main(argv, prog)`` function, one-line description)
VERBS: dict[str, tuple[str, str]] = {
    "demos": ("cotpc.cli.demos", "Generate demonstrations of a task suite in ManiSkill3's trajectory format."),
    "train": ("cotpc.cli.train", "Train a policy (bc, dt, bet, cotpc or an ablation) on a demonstration file."),
    "eval": ("cotpc.cli.eval", "Roll a trained policy out on seen or unseen configs; success rate with a 95% CI."),
    "segment": ("cotpc.cli.segment", "Discover subskills (exact DP) and store traj_<i>/subskill_ends in a trajectory file."),
    "reproduce": ("cotpc.cli.reproduce", "The whole study in one command: demos, subskills, training, evaluation, report."),
    "bench": ("cotpc.cli.bench", "Micro-benchmarks (segment, ...): timings and quality against reference tools."),
}


def usage() -> str:
    lines = ["usage: cotpc VERB [--help] ...", "", "Chain-of-Thought Predictive Control.", "", "verbs:"]
    lines += [f"  {verb:<10} {desc}" for verb, (_, desc) in VERBS.items()]
    lines += ["", "Run `cotpc VERB --help` for the flags of each verb."]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] in ("-h", "--help"):
        print(usage())
        return
    if argv[0] == "--version":
        print(__version__)
        return
    verb = argv[0]
    if verb not in VERBS:
        print(f"cotpc: unknown verb {verb!r}\n\n{usage()}", file=sys.stderr)
        raise SystemExit(2)
    module = importlib.import_module(VERBS[verb][0])
    module.main(argv[1:], prog=f"cotpc {verb}")


if __name__ == "__main__":
    main()
