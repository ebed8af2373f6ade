"""The Markovian BC baseline as a policy family: a 3-layer MLP (hidden 256) from the current state to the action,
trained with MSE (paper appendix: lr 1e-3, batch 32)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch
import torch.nn as nn

from cotpc.policies.base import BaseConfig, Normaliser, mlp, register_family


@dataclass(frozen=True)
class MLPConfig(BaseConfig):
    """Markovian BC."""

    name: str = "bc"
    hidden: int = 256
    """Hidden width of the two hidden layers."""
    lr: float = 1e-3
    min_lr: float = 1e-3
    schedule: Literal["cosine", "constant"] = "constant"
    warmup_iters: int = 0
    batch_size: int = 32
    weight_decay: float = 0.0

    @property
    def action_head(self) -> str:  # read by the reports; the same name as the transformer's MSE head
        return "mse"


class MLPPolicy(nn.Module):
    """Markovian BC: a 3-layer MLP (hidden 256) from the current state to the action, MSE."""

    def __init__(self, cfg: MLPConfig, obs_dim: int, action_dim: int, max_timestep: int = 0):
        super().__init__()
        self.cfg, self.obs_dim, self.action_dim = cfg, obs_dim, action_dim
        self.norm = Normaliser(obs_dim, action_dim)
        self.net = mlp([obs_dim, cfg.hidden, cfg.hidden, action_dim])

    def forward(self, batch: dict):
        return self.loss(batch)

    def loss(self, batch: dict) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        pred = self.net(batch["states"][:, -1]).float()
        mse = ((pred - batch["actions"][:, -1]) ** 2).mean()
        return mse, {"mse": mse, "bc": mse, "loss": mse}

    def predict(self, batch: dict) -> torch.Tensor:
        return self.net(batch["states"][:, -1]).float()

    @torch.no_grad()
    def inference_metrics(self, batch: dict) -> dict[str, torch.Tensor]:
        """As :meth:`TransformerPolicy.inference_metrics`; Markovian, so the same as its loss."""
        err = ((self.predict(batch) - batch["actions"][:, -1]) ** 2).mean()
        return {"bc": err, "action_err": err}

    @torch.no_grad()
    def validation_metrics(self, batch: dict) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
        return self.loss(batch)[1], self.inference_metrics(batch)


register_family("mlp", MLPConfig, MLPPolicy, presets={"bc": MLPConfig()})
