"""Average the weights of a run's last N kept checkpoints into a new run directory that `cotpc eval` loads.

An exploratory tool (docs/results/maze.md, fifth session): a uniform average over the end of a cosine schedule,
the cheap stand-in for an exponential moving average of the weights. Buffers that are not trained (k-means
centres, normalisation statistics) are the same in every checkpoint; integer tensors are taken from the last.

    .venv/bin/python scripts/average-checkpoints.py RUN N OUT
    .venv/bin/cotpc eval OUT --split val
"""

import argparse
import shutil
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="a run directory trained with --keep-checkpoints")
    parser.add_argument("n", type=int, help="how many of the last kept checkpoints to average")
    parser.add_argument("out", type=Path, help="new run directory (config.json + model.safetensors)")
    args = parser.parse_args()
    steps = sorted((args.run / "checkpoints").glob("step_*"))
    if args.n < 1 or len(steps) < args.n:
        raise SystemExit(f"{args.run}: {len(steps)} kept checkpoints, asked to average {args.n}")
    steps = steps[-args.n:]
    states = [load_file(str(s / "model.safetensors")) for s in steps]
    if any(set(sd) != set(states[0]) for sd in states):
        raise SystemExit(f"{args.run}: the checkpoints hold different tensors; not one run's")
    averaged = {k: (sum(sd[k].double() for sd in states) / len(states)).to(t.dtype) if t.is_floating_point() else
                states[-1][k] for k, t in states[0].items()}
    args.out.mkdir(parents=True, exist_ok=True)
    shutil.copy(steps[-1] / "config.json", args.out / "config.json")
    save_file(averaged, str(args.out / "model.safetensors"))
    print(args.out, "<-", ", ".join(s.name for s in steps))


if __name__ == "__main__":
    torch.set_num_threads(1)
    main()
