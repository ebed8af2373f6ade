"""Policy networks: the transformer policy (DT, BeT, CoTPC and its ablations) and the BC MLP.

Both take *normalised* tensors. The normalisation statistics and the k-means centres are buffers, so they are
saved in ``model.safetensors`` with the weights.

A training batch is a dict of
``states`` (B,T,q), ``actions`` (B,T,p), ``timesteps`` (B,T) long, ``valid`` (B,T) bool (False = left padding),
``cot`` (B,T,k*q) CoT targets (when the policy predicts a CoT) and ``cot_hide`` (B,) long (the random l).
"""

from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

from cotpc.policies.config import PolicyConfig
from cotpc.policies.transformer import GPT, mlp


def _masked_mean(x: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    w = valid.to(x.dtype)
    return (x * w).sum() / w.sum().clamp_min(1.0)


class Normaliser(nn.Module):
    """Observation and action statistics (buffers, saved in the checkpoint)."""

    def __init__(self, obs_dim: int, action_dim: int):
        super().__init__()
        self.register_buffer("obs_mean", torch.zeros(obs_dim))
        self.register_buffer("obs_std", torch.ones(obs_dim))
        self.register_buffer("act_mean", torch.zeros(action_dim))
        self.register_buffer("act_std", torch.ones(action_dim))


class TransformerPolicy(nn.Module):
    def __init__(self, cfg: PolicyConfig, obs_dim: int, action_dim: int, max_timestep: int):
        super().__init__()
        self.cfg, self.obs_dim, self.action_dim = cfg, obs_dim, action_dim
        self.norm = Normaliser(obs_dim, action_dim)
        d, h, p = cfg.d_model, cfg.hidden, action_dim
        n_cot = cfg.n_cot_tokens
        n_targets = len(cfg.cot_targets)
        if cfg.decoupled:
            # The CoT transformer: CoT tokens + CoT decoder only. Its prediction [s_next, s_last] is fed, with the
            # state, to the state encoder of a BeT-style action transformer.
            self.cot_gpt = GPT(cfg, obs_dim, action_dim, max_timestep, n_cot)
            self.gpt = GPT(cfg, obs_dim + n_targets * obs_dim, action_dim, max_timestep, 0)
        else:
            self.gpt = GPT(cfg, obs_dim, action_dim, max_timestep, n_cot)
        self.cot_head = mlp([d, h, n_targets * obs_dim]) if n_targets else None
        if cfg.action_head == "bet":
            self.centre_head = mlp([d, h, h, cfg.n_centres])
            self.offset_head = mlp([d, h, h, cfg.n_centres * p])
            self.register_buffer("centres", torch.zeros(cfg.n_centres, p))
        else:
            self.action_decoder = mlp([d, h, h, p])
        self.apply(_init_weights)
        self.cot_layer = cfg.cot_layer % cfg.n_layers

    # --- features -------------------------------------------------------------------------------------------
    def _predict_cot(self, gpt: GPT, states, actions, timesteps, valid, cot_hide):
        x, kept = gpt(states, actions, timesteps, valid, cot_hide, keep_layer=self.cot_layer)
        return x, self.cot_head(kept[:, : gpt.layout.C])

    def _features(self, batch: dict, train: bool):
        """Run the transformer(s); return final features, the CoT prediction (or None) and the layout."""
        states, actions = batch["states"], batch["actions"][:, :-1] if self.cfg.use_actions else None
        timesteps, valid = batch["timesteps"], batch.get("valid")
        cot_hide = batch.get("cot_hide") if (train and self.cfg.random_cot_mask) else None
        cot_pred = None
        if self.cfg.decoupled:
            _, cot_pred = self._predict_cot(self.cot_gpt, states, actions, timesteps, valid, cot_hide)
            # the action transformer sees the CoT transformer's prediction, not the ground truth; no gradient
            # flows back: the two transformers are trained by their own losses (decoupled)
            states = torch.cat([states, cot_pred.detach().to(states.dtype)], dim=-1)
            x, _ = self.gpt(states, actions, timesteps, valid)
        elif self.cot_head is not None:
            x, cot_pred = self._predict_cot(self.gpt, states, actions, timesteps, valid, cot_hide)
        else:
            x, _ = self.gpt(states, actions, timesteps, valid, cot_hide if self.gpt.layout.C else None)
        return x, cot_pred

    def _select(self, x: torch.Tensor, source: str, valid: torch.Tensor | None) -> torch.Tensor:
        """(B, T, d) features that predict the action of each window index."""
        lay = self.gpt.layout
        state_feats = x[:, lay.state_pos]
        if source == "state":
            return state_feats
        if source == "cot":
            return x[:, : lay.C]
        # "action": the action token a(i-1) just before s(i). Window index 0, and an a(i-1) that is padding,
        # have none: their state token is used instead.
        idx = (lay.state_pos - 1).clamp(min=lay.C)
        act_feats = x[:, idx]
        has_prev = torch.arange(lay.T, device=x.device) > 0
        has_prev = has_prev[None, :] & (valid.roll(1, dims=1) if valid is not None else True)
        return torch.where(has_prev[..., None], act_feats, state_feats)

    # --- training ---------------------------------------------------------------------------------------------
    def forward(self, batch: dict):
        return self.loss(batch)

    def loss(self, batch: dict) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        cfg = self.cfg
        valid = batch["valid"]
        x, cot_pred = self._features(batch, train=True)
        target = batch["actions"]  # normalised
        metrics = {}
        if cfg.action_head == "mse":
            pred = self.action_decoder(self._select(x, cfg.centre_from, valid)).float()
            bc = _masked_mean(((pred - target) ** 2).mean(-1), valid)
            metrics["mse"] = bc
        else:
            logits = self.centre_head(self._select(x, cfg.centre_from, valid)).float()  # (B,T,K)
            offsets = self.offset_head(self._select(x, cfg.offset_from, valid)).float()
            offsets = offsets.view(*offsets.shape[:2], cfg.n_centres, self.action_dim)
            true_c = torch.cdist(target, self.centres[None].expand(target.shape[0], -1, -1)).argmin(-1)  # (B,T)
            ce = F.cross_entropy(logits.flatten(0, 1), true_c.flatten(), reduction="none").view_as(true_c)
            off = torch.gather(offsets, 2, true_c[..., None, None].expand(-1, -1, 1, self.action_dim))[:, :, 0]
            off_mse = ((off - (target - self.centres[true_c])) ** 2).mean(-1)
            metrics["ce"], metrics["offset"] = _masked_mean(ce, valid), _masked_mean(off_mse, valid)
            bc = metrics["ce"] + cfg.offset_weight * metrics["offset"]
        total = bc
        metrics["bc"] = bc
        if cot_pred is not None:
            cot_t, cot_valid = batch["cot"], valid
            if cot_pred.shape[1] == 1:  # one CoT token (vanilla): it predicts the CoT of the current timestep
                cot_t, cot_valid = cot_t[:, -1:], valid[:, -1:]
            metrics["cot"] = _masked_mean(((cot_pred.float() - cot_t) ** 2).mean(-1), cot_valid)
            total = total + cfg.cot_weight * metrics["cot"]
        metrics["loss"] = total
        return total, metrics

    # --- inference --------------------------------------------------------------------------------------------
    def _last_features(self, batch: dict) -> dict[str, torch.Tensor]:
        """(B, d) features of the last window index for each source the action heads read.

        The same values as ``_select(features, source)[:, -1]``, but the last block computes only the tokens
        read: the state token s(T-1), the CoT token T-1 and the action token a(T-2)."""
        cfg, lay = self.cfg, self.gpt.layout
        sources = {cfg.centre_from} | ({cfg.offset_from} if cfg.action_head == "bet" else set())
        if "action" in sources:
            sources.add("state")  # an action token that is missing or padding falls back to the state token
        s_row = int(lay.state_pos[-1])
        rows = {src: {"state": s_row, "cot": lay.C - 1, "action": max(s_row - 1, 0)}[src] for src in sorted(sources)}
        states, actions = batch["states"], batch["actions"][:, :-1] if cfg.use_actions else None
        timesteps, valid = batch["timesteps"], batch.get("valid")
        if cfg.decoupled:  # the CoT transformer's prediction is an input of the action transformer
            _, cot_pred = self._predict_cot(self.cot_gpt, states, actions, timesteps, valid, None)
            states = torch.cat([states, cot_pred.to(states.dtype)], dim=-1)
        row_index = torch.tensor(list(rows.values()), device=states.device)
        x, _ = self.gpt(states, actions, timesteps, valid, rows=row_index)  # (B, len(rows), d)
        feats = {src: x[:, i] for i, src in enumerate(rows)}
        if "action" in feats:
            has_prev = valid[:, -2] if (valid is not None and lay.T > 1) else torch.tensor(lay.T > 1)
            feats["action"] = torch.where(has_prev.reshape(-1, 1), feats["action"], feats["state"])
        return feats

    def predict(self, batch: dict) -> torch.Tensor:
        """Normalised action (B, p) for the last window index (no random CoT mask)."""
        cfg = self.cfg
        feats = self._last_features(batch)
        if cfg.action_head == "mse":
            return self.action_decoder(feats[cfg.centre_from]).float()
        logits = self.centre_head(feats[cfg.centre_from]).float()
        offsets = self.offset_head(feats[cfg.offset_from]).float()
        c = logits.argmax(-1)
        off = offsets.view(-1, cfg.n_centres, self.action_dim)[torch.arange(c.shape[0], device=c.device), c]
        return self.centres[c] + off


class MLPPolicy(nn.Module):
    """Markovian BC: a 3-layer MLP (hidden 256) from the current state to the action, MSE."""

    def __init__(self, cfg: PolicyConfig, obs_dim: int, action_dim: int, max_timestep: int = 0):
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


def _init_weights(m: nn.Module) -> None:
    # GPT-2 / minGPT initialisation, as in the official CoTPC code
    if isinstance(m, (nn.Linear, nn.Embedding)):
        nn.init.normal_(m.weight, std=0.02)
        if isinstance(m, nn.Linear) and m.bias is not None:
            nn.init.zeros_(m.bias)
    elif isinstance(m, GPT):
        if m.cot_tokens is not None:
            nn.init.normal_(m.cot_tokens, std=0.02)


def make_model(cfg: PolicyConfig, obs_dim: int, action_dim: int, max_timestep: int) -> nn.Module:
    """Build the network of a policy configuration."""
    cfg.validate()
    if cfg.arch == "mlp":
        return MLPPolicy(cfg, obs_dim, action_dim, max_timestep)
    return TransformerPolicy(cfg, obs_dim, action_dim, max_timestep)
