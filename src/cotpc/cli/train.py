"""``cotpc train``: train a policy (see :class:`cotpc.training.TrainConfig` for every flag)."""

from __future__ import annotations


def main(argv: list[str], prog: str) -> None:
    from cotpc.training.train import main as train_main

    train_main(argv, prog=prog)
