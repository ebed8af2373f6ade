"""``cotpc train``: train a policy (see :class:`cotpc.training.TrainConfig` for every flag)."""

from __future__ import annotations

from cotpc.training.train import main as train_main


def main(argv: list[str], prog: str) -> None:
    train_main(argv, prog=prog)
