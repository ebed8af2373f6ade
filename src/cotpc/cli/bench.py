"""``cotpc bench NAME``: reproducible micro-benchmarks, one module per NAME exposing ``main(argv, prog)``."""

from __future__ import annotations

import importlib
import sys

# benchmark -> (module with a ``main(argv, prog)`` function, one-line description)
BENCHES: dict[str, tuple[str, str]] = {
    "segment": (
        "cotpc.bench.segment",
        "Exact batched subskill discovery vs ruptures' PELT on synthetic actions: seconds and objectives.",
    ),
    "train": ("cotpc.bench.train", "ms per training iteration of every policy (the paper's task shapes), GFLOP/s."),
    "act": ("cotpc.bench.act", "ms per select_action at batch 1 and 100."),
}


def usage(prog: str) -> str:
    lines = [f"usage: {prog} NAME [--help] ...", "", "benchmarks:"]
    lines += [f"  {name:<10} {desc}" for name, (_, desc) in BENCHES.items()]
    lines += ["", f"Run `{prog} NAME --help` for the flags of each benchmark."]
    return "\n".join(lines)


def main(argv: list[str], prog: str = "cotpc bench") -> None:
    if not argv or argv[0] in ("-h", "--help"):
        print(usage(prog))
        return
    if argv[0] not in BENCHES:
        print(f"{prog}: unknown benchmark {argv[0]!r}\n\n{usage(prog)}", file=sys.stderr)
        raise SystemExit(2)
    module = importlib.import_module(BENCHES[argv[0]][0])
    module.main(argv[1:], prog=f"{prog} {argv[0]}")
