"""Module entry for multi-process training: ``torchrun --nproc_per_node=N -m cotpc.train --data ... ``."""

from cotpc.training.train import main

if __name__ == "__main__":
    main(prog="torchrun -m cotpc.train")
