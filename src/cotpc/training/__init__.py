"""Training: ``train(TrainConfig) -> run_dir``; ``cotpc train`` and ``torchrun -m cotpc.train`` call it."""

from cotpc.training.train import TrainConfig, evaluate_loss, train

__all__ = ["TrainConfig", "evaluate_loss", "train"]
