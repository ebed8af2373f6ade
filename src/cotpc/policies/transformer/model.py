"""The transformer family's network: the policy of DT, BeT, CoTPC and its ablations (registered as the family
``transformer`` with :class:`~cotpc.policies.transformer.config.TransformerConfig`).

It takes *normalised* tensors. The normalisation statistics and the k-means centres are buffers, so they are
saved in ``model.safetensors`` with the weights.

A training batch is a dict of
``states`` (B,T,q), ``actions`` (B,T,p), ``timesteps`` (B,T) long, ``valid`` (B,T) bool (False = left padding),
``cot`` (B,T,k*q) CoT targets (when the policy predicts a CoT) and ``cot_hide`` (B,) long (the random l); with
``action_chunk`` k > 1 also ``future_actions`` (B,k-1,p), the actions after the window's last one.

With ``action_chunk`` k > 1 every head predicts k actions per window index, a(i) .. a(i+k-1) (the bet head: a
centre and its offset for each of the k steps, k groups of K classes), and the losses average over the chunk.
"""

from __future__ import annotations

import math
import warnings

import torch
import torch.nn as nn
import torch.nn.functional as F

from cotpc.policies.base import Normaliser, mlp, register_family
from cotpc.policies.transformer.config import TRANSFORMER_PRESETS, TransformerConfig
from cotpc.policies.transformer.backbone import GPT, run_mlp


class RowGatheredLinear(torch.autograd.Function):
    """``linear(x, weight, bias).view(N, K, p)[arange(N), rows]`` without computing the other K - 1 groups.

    x (N, h), weight (K * p, h), bias (K * p,), rows (N,) long in [0, K) -> (N, p), in fp32; or rows (N, k),
    ascending (k groups per row: a chunk's steps, which share x), -> (N, k, p). The dense layer is
    K x p x h multiply-adds per token, most of the offset head's cost, and only p of its K x p outputs reach the
    loss (K = 1024 in the maze; k x 128 with action chunks on ManiSkill). The p outputs of row n are a sparse
    pattern S of the dense (N, K p) product: the forward samples it (``sampled_addmm``), and the backward's
    dx = S @ weight and dweight = S^T @ x are sparse-dense products. Gathering each row's (p, h) weights
    instead (a (N, p, h) copy, batched matmuls, outer products added back) took ~13x longer on a CPU
    (N = 20480, p = 8, h = 256, K p = 8192: 40 against 530 ms forward and backward, one core)."""

    @staticmethod
    def forward(ctx, x, weight, bias, rows, p: int):
        n = x.shape[0]
        # row n's outputs: p per group in rows[n] ((N,) or (N, k), one group per chunk step, ascending)
        cols = (rows.view(n, -1, 1) * p + torch.arange(p, device=x.device)).flatten()
        m = cols.numel() // n
        x32 = x.float()
        with warnings.catch_warnings():  # torch calls the CSR layout beta; tested against the dense layer here
            warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta state")
            pattern = torch.sparse_csr_tensor(torch.arange(0, n * m + 1, m, device=x.device), cols,
                                              torch.zeros(n * m, device=x.device), (n, weight.shape[0]),
                                              check_invariants=False)  # built valid: sorted columns per row
        out = torch.sparse.sampled_addmm(pattern, x32, weight.float().t(), beta=0.0).values()
        ctx.save_for_backward(x32, weight, rows, cols)
        ctx.x_dtype, ctx.p = x.dtype, p
        return out.view(*rows.shape, p) + bias.view(-1, p)[rows]

    @staticmethod
    def backward(ctx, d):
        x32, weight, rows, cols = ctx.saved_tensors
        p, n, kp = ctx.p, x32.shape[0], weight.shape[0]
        d = d.float().contiguous()
        entries = torch.arange(n, device=d.device).repeat_interleave(cols.numel() // n)
        s = torch.sparse_coo_tensor(torch.stack([entries, cols]), d.flatten(), (n, kp), check_invariants=False)
        dx = torch.sparse.mm(s, weight.float()).to(ctx.x_dtype)
        dw = torch.sparse.mm(s.t(), x32)
        db = torch.zeros(kp // p, p, device=d.device).index_add_(0, rows.flatten(), d.view(-1, p))
        return dx, dw, db.view(kp), None, None


def _dense_offsets_pay(x: torch.Tensor, n_centres: int) -> bool:
    """Whether the offset head's full K x p output (then the true centre's p values) beats gathering each row's
    (p, h) weights (:class:`RowGatheredLinear`). The dense layer costs K x p x h multiply-adds per row but only
    K x p values of memory traffic; the gather costs p x h values per row, and on a CPU memory traffic, not
    arithmetic, bounds both once matmuls are fast: under bf16 autocast (chosen only where the bf16 step was timed
    faster: AMX or a GPU) or on CUDA, and K <= h. Measured on an AMX Xeon, batch 256, alternating rounds: CoTPC
    ManiSkill shape (K 128, h 256) dense 5% faster; BeT maze shape (K 1024) dense 12% slower."""
    fast = x.device.type == "cuda" or torch.is_autocast_enabled(x.device.type)
    return fast and n_centres <= x.shape[-1]


GMM_MIN_STD = 0.01  # floor of the gmm head's standard deviations (normalised units, robomimic's): no collapse


def _masked_mean(x: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    w = valid.to(x.dtype)
    return (x * w).sum() / w.sum().clamp_min(1.0)


class TransformerPolicy(nn.Module):
    # Validation scores at most this many held-out windows, evenly spaced (evaluate_loss): with every window of a
    # 1600-demo maze file (~6,600) the ten validations of a 1500-iteration run took 24% of its wall time
    # (docs/performance.md); 1024 windows keep it under a tenth. `cotpc train --val-windows` overrides it.
    validation_windows = 1024

    def __init__(self, cfg: TransformerConfig, obs_dim: int, action_dim: int, max_timestep: int):
        super().__init__()
        self.cfg, self.obs_dim, self.action_dim = cfg, obs_dim, action_dim
        self.norm = Normaliser(obs_dim, action_dim)
        self._draws: torch.Generator | None = None  # action_rule="sample" only (draw_mode)
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
        k = cfg.action_chunk  # actions predicted per window index, each with its own outputs
        if cfg.action_head == "bet":
            self.centre_head = mlp([d, h, h, k * cfg.n_centres])
            self.offset_head = mlp([d, h, h, k * cfg.n_centres * p])
            self.register_buffer("centres", torch.zeros(cfg.n_centres, p))
        elif cfg.action_head == "gmm":  # per mode: a logit, a mean (p) and a standard deviation (p)
            self.mixture_head = mlp([d, h, h, k * cfg.n_modes * (1 + 2 * p)])
        else:
            self.action_decoder = mlp([d, h, h, k * p])
        self.apply(_init_weights)
        self.cot_layer = cfg.cot_layer % cfg.n_layers
        self._rows = self._train_rows()
        rows, lay = self._rows[0], self.gpt.layout
        row_of = torch.arange(lay.length)  # token position -> its index among the rows (-1: not computed)
        if rows is not None:
            row_of = torch.full((lay.length,), -1, dtype=torch.long)
            row_of[rows] = torch.arange(len(rows))
        self.register_buffer("row_of", row_of, persistent=False)
        # inference: the sources the action heads read at the last window index, and their last-block rows
        self._last_sources, last = self._inference_rows()
        self._last_slice = last if isinstance(last, slice) else None
        self.register_buffer("last_rows", last if isinstance(last, torch.Tensor) else None, persistent=False)

    # --- features -------------------------------------------------------------------------------------------
    def _predict_cot(self, gpt: GPT, states, actions, timesteps, valid, cot_hide, rows=None):
        x, kept = gpt(states, actions, timesteps, valid, cot_hide, keep_layer=self.cot_layer, rows=rows)
        return x, self.cot_head(kept[:, : gpt.layout.C])

    def _train_rows(self) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        """Token positions the training losses read from the last block of the action transformer (and of the
        CoT transformer when decoupled), or None for all. The other tokens of the last block feed nothing, so
        skipping them changes no loss or gradient (tested) and saves a part of the last block's work."""
        cfg, lay = self.cfg, self.gpt.layout
        last = self.cot_layer == self.cfg.n_layers - 1
        sources = {cfg.centre_from} | ({cfg.offset_from} if cfg.action_head == "bet" else set())
        need = torch.zeros(lay.length, dtype=torch.bool)
        need[lay.state_pos] = True  # the state token is also the fallback of a missing action token
        if "cot" in sources or (self.cot_head is not None and not cfg.decoupled and last):
            need[: lay.C] = True
        if "action" in sources:
            need[lay.action_pos] = True
        rows = None if bool(need.all()) else need.nonzero()[:, 0]
        cot_rows = torch.arange(self.cot_gpt.layout.C) if (cfg.decoupled and last) else None
        return rows, cot_rows

    def _features(self, batch: dict, train: bool):
        """Run the transformer(s); return the final features of the rows the losses read (see
        :meth:`_train_rows`; (B, L, d) when all are read) and the CoT prediction (or None)."""
        states, actions = batch["states"], batch["actions"][:, :-1] if self.cfg.use_actions else None
        timesteps, valid = batch["timesteps"], batch.get("valid")
        cot_hide = batch.get("cot_hide") if (train and self.cfg.random_cot_mask) else None
        rows, cot_rows = self._rows
        rows = None if rows is None else rows.to(states.device)
        cot_pred = None
        if self.cfg.decoupled:
            cot_rows = None if cot_rows is None else cot_rows.to(states.device)
            _, cot_pred = self._predict_cot(self.cot_gpt, states, actions, timesteps, valid, cot_hide, cot_rows)
            # the action transformer sees the CoT transformer's prediction, not the ground truth; no gradient
            # flows back: the two transformers are trained by their own losses (decoupled)
            states = torch.cat([states, cot_pred.detach().to(states.dtype)], dim=-1)
            x, _ = self.gpt(states, actions, timesteps, valid, rows=rows)
        elif self.cot_head is not None:
            x, cot_pred = self._predict_cot(self.gpt, states, actions, timesteps, valid, cot_hide, rows)
        else:
            x, _ = self.gpt(states, actions, timesteps, valid, cot_hide if self.gpt.layout.C else None, rows=rows)
        return x, cot_pred

    def _select(self, x: torch.Tensor, source: str, valid: torch.Tensor | None) -> torch.Tensor:
        """(B, T, d) features that predict the action of each window index, from the features of the rows
        :meth:`_train_rows` chose (``x`` is (B, len(rows), d), or (B, L, d) for all)."""
        lay, where = self.gpt.layout, self.row_of
        state_feats = x[:, where[lay.state_pos]]
        if source == "state":
            return state_feats
        if source == "cot":
            return x[:, where[: lay.C]]
        # "action": the action token a(i-1) just before s(i). Window index 0, and an a(i-1) that is padding,
        # have none: their state token is used instead.
        idx = (lay.state_pos - 1).clamp(min=lay.C)
        act_feats = x[:, where[idx].clamp(min=0)]
        has_prev = torch.arange(lay.T, device=x.device) > 0
        has_prev = has_prev[None, :] & (valid.roll(1, dims=1) if valid is not None else True)
        return torch.where(has_prev[..., None], act_feats, state_feats)

    def _true_centre_offsets(self, feats: torch.Tensor, centre: torch.Tensor) -> torch.Tensor:
        """The offset head's output for the given centres only: (..., d) features, (..., k) centres (one per
        chunk step) -> (..., k, p).

        Equal to reading the full (k x K x p) output at ``centre``, without computing the offsets no loss
        reads (the full last layer is k x K x p x hidden multiply-adds per token: most of the head's cost)."""
        hidden = self.offset_head[:-1](feats)  # (..., h)
        last, p, K = self.offset_head[-1], self.action_dim, self.cfg.n_centres
        if _dense_offsets_pay(hidden, centre.shape[-1] * K):  # the dense layer, then the true centres' outputs
            full = last(hidden).view(*centre.shape, K, p)  # (..., k, K, p)
            index = centre[..., None, None].expand(*centre.shape, 1, p)
            return full.gather(-2, index)[..., 0, :]
        rows = centre + K * torch.arange(centre.shape[-1], device=centre.device)  # chunk step j's group of K
        flat = rows.reshape(-1, rows.shape[-1])  # one row of x per token, shared by its chunk's k groups
        off = RowGatheredLinear.apply(hidden.reshape(len(flat), -1), last.weight, last.bias, flat, p)
        return off.view(*centre.shape, p)

    def _chunk_targets(self, batch: dict) -> torch.Tensor:
        """(B, T, k, p) normalised targets: a(i) .. a(i+k-1) for each window index i, from the window's actions
        and its ``future_actions`` (the episode's last action repeated past its end)."""
        k, actions = self.cfg.action_chunk, batch["actions"]
        if k == 1:
            return actions[:, :, None]
        future = batch.get("future_actions")
        if future is None or future.shape[1] < k - 1:
            raise ValueError(f"action_chunk={k} needs windows with {k - 1} future actions "
                             f"(WindowDataset(future_actions={k - 1}))")
        return torch.cat([actions, future[:, : k - 1]], dim=1).unfold(1, k, 1).transpose(-1, -2)

    def _nearest_centre(self, target: torch.Tensor) -> torch.Tensor:
        """Index of the k-means centre nearest each (normalised) action: (B, ..., p) -> (B, ...)."""
        flat = target.flatten(1, -2)
        return torch.cdist(flat, self.centres[None].expand(flat.shape[0], -1, -1)).argmin(-1).view(target.shape[:-1])

    def mixture(self, raw: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The gmm head's output (..., M (1 + 2p)) as mode logits (..., M), means and standard deviations
        (..., M, p), in fp32."""
        m, p = self.cfg.n_modes, self.action_dim
        logits, means, stds = raw.float().split([m, m * p, m * p], dim=-1)
        return logits, means.unflatten(-1, (m, p)), F.softplus(stds.unflatten(-1, (m, p))) + GMM_MIN_STD

    def mixture_nll(self, raw: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """Negative log-likelihood (...) of the (normalised) target actions (..., p) under the gmm head's output."""
        logits, means, stds = self.mixture(raw)
        z = (target.float()[..., None, :] - means) / stds
        log_component = (-0.5 * z**2 - stds.log() - 0.5 * math.log(2 * math.pi)).sum(-1)
        return -torch.logsumexp(F.log_softmax(logits, dim=-1) + log_component, dim=-1)

    def mixture_mode(self, raw: torch.Tensor) -> torch.Tensor:
        """The action the gmm head acts with: the mean of its most likely mode (deterministic, so rollouts are
        reproducible and no sampling noise enters evaluation). (..., M (1 + 2p)) -> (..., p)."""
        logits, means, _ = self.mixture(raw)
        k = logits.argmax(-1)[..., None, None].expand(*logits.shape[:-1], 1, self.action_dim)
        return means.gather(-2, k)[..., 0, :]

    def mixture_mean(self, raw: torch.Tensor) -> torch.Tensor:
        """The mixture's expected action (``action_rule="mean"``). (..., M (1 + 2p)) -> (..., p)."""
        logits, means, _ = self.mixture(raw)
        return (logits.softmax(-1)[..., None] * means).sum(-2)

    def draw_mode(self, logits: torch.Tensor) -> torch.Tensor:
        """``action_rule="sample"``: a mode index (B,) drawn from softmax(logits) (B, K) with the model's own
        generator, seeded 0 when the model is built or loaded, so an evaluation repeats exactly."""
        if self._draws is None or self._draws.device != logits.device:
            self._draws = torch.Generator(device=logits.device).manual_seed(0)
        return torch.multinomial(logits.float().softmax(-1), 1, generator=self._draws)[:, 0]

    # --- training ---------------------------------------------------------------------------------------------
    def forward(self, batch: dict):
        return self.loss(batch)

    def loss(self, batch: dict) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """The training loss (random CoT mask drawn per sample) and its terms, averaged over window positions."""
        x, cot_pred = self._features(batch, train=True)
        return self._loss_terms(x, cot_pred, batch)

    @torch.no_grad()
    def validation_metrics(self, batch: dict) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
        """One pass without the random mask: (loss terms over all window positions, the metrics of
        :meth:`inference_metrics` at the last position, read from the same features)."""
        cfg = self.cfg
        x, cot_pred = self._features(batch, train=False)
        _, all_positions = self._loss_terms(x, cot_pred, batch)
        srcs = {cfg.centre_from, cfg.offset_from}
        feats = {src: self._select(x, src, batch.get("valid"))[:, -1] for src in srcs}
        return all_positions, self._last_metrics(feats, batch, cot_pred[:, -1] if cot_pred is not None else None)

    def _loss_terms(self, x, cot_pred, batch: dict) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        cfg = self.cfg
        valid = batch["valid"]
        target = self._chunk_targets(batch)  # (B, T, k, p), normalised
        k = target.shape[2]
        metrics = {}
        if cfg.action_head == "mse":
            pred = self.action_decoder(self._select(x, cfg.centre_from, valid)).float().unflatten(-1, (k, -1))
            bc = _masked_mean(((pred - target) ** 2).mean((-2, -1)), valid)
            metrics["mse"] = bc
        elif cfg.action_head == "gmm":
            raw = self.mixture_head(self._select(x, cfg.centre_from, valid)).unflatten(-1, (k, -1))
            bc = _masked_mean(self.mixture_nll(raw, target).mean(-1), valid)
            metrics["nll"] = bc
        else:
            logits = self.centre_head(self._select(x, cfg.centre_from, valid)).float().unflatten(-1, (k, -1))
            true_c = self._nearest_centre(target)  # (B, T, k)
            off = self._true_centre_offsets(self._select(x, cfg.offset_from, valid), true_c).float()
            ce = F.cross_entropy(logits.flatten(0, 2), true_c.flatten(), reduction="none").view_as(true_c).mean(-1)
            off_mse = ((off - (target - self.centres[true_c])) ** 2).mean((-2, -1))
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
    # Inference runs GPT.infer: the values of the training forward at the last window index, in fewer ops (no
    # autograd bookkeeping, the last block on the tokens read only, the CoT transformer up to its CoT layer).
    def _inference_rows(self) -> tuple[tuple[str, ...], slice | torch.Tensor]:
        """The sources the action heads read at the last window index and their token rows in the last block:
        the state token s(T-1), the CoT token T-1 and the action token a(T-2) (a slice when consecutive)."""
        cfg, lay = self.cfg, self.gpt.layout
        sources = {cfg.centre_from} | ({cfg.offset_from} if cfg.action_head == "bet" else set())
        if "action" in sources:
            sources.add("state")  # an action token that is missing or padding falls back to the state token
        s_row = int(lay.state_pos[-1])
        order = tuple(sorted(sources))
        rows = [{"state": s_row, "cot": lay.C - 1, "action": max(s_row - 1, 0)}[src] for src in order]
        if rows == list(range(rows[0], rows[0] + len(rows))):
            return order, slice(rows[0], rows[0] + len(rows))  # a view, no gather
        return order, torch.tensor(rows)

    def _infer_features(self, states, actions, timesteps, valid=None, n_prev=None) -> dict[str, torch.Tensor]:
        """(B, d) features of the last window index for each source the action heads read. states (B, T, q),
        actions (B, T-1, p) (None without action tokens), timesteps (B, T); left padding as ``valid`` (B, T) or
        ``n_prev`` (B,), see :meth:`GPT.inference_bias`."""
        cfg, lay = self.cfg, self.gpt.layout
        if cfg.decoupled:  # the CoT transformer's prediction is an input of the action transformer
            cot = self.cot_gpt
            kept = cot.infer(states, actions, timesteps, cot.inference_bias(valid, n_prev), rows=slice(0, cot.layout.C),
                             n_blocks=self.cot_layer + 1)  # its later blocks feed nothing here
            states = torch.cat([states, run_mlp(self.cot_head, kept).to(states.dtype)], dim=-1)
        rows = self._last_slice if self._last_slice is not None else self.last_rows
        x = self.gpt.infer(states, actions, timesteps, self.gpt.inference_bias(valid, n_prev), rows=rows)
        x = F.layer_norm(x, x.shape[-1:], self.gpt.ln_f.weight, self.gpt.ln_f.bias, self.gpt.ln_f.eps)
        feats = {src: x[:, i] for i, src in enumerate(self._last_sources)}
        if "action" in feats:
            if lay.T == 1:  # no earlier action token
                feats["action"] = feats["state"]
            elif n_prev is not None or valid is not None:
                has_prev = (n_prev >= 1) if n_prev is not None else valid[:, -2]
                feats["action"] = torch.where(has_prev.reshape(-1, 1), feats["action"], feats["state"])
        return feats

    def _last_features(self, batch: dict) -> dict[str, torch.Tensor]:
        """(B, d) features of the last window index for each source the action heads read: the same values as
        ``_select(features, source)[:, -1]`` of the training forward (tested)."""
        actions = batch["actions"][:, :-1] if self.cfg.use_actions else None
        return self._infer_features(batch["states"], actions, batch["timesteps"], batch.get("valid"))

    @torch.no_grad()
    def inference_metrics(self, batch: dict) -> dict[str, torch.Tensor]:
        """Per-head metrics at the last window index, without the random CoT mask: the regime ``select_action``
        meets, where no target is visible (SPEC section 4: at the other positions the paper's hybrid mask lets
        CoT tokens see the action being predicted, so losses averaged over all positions measure that leak).

        ``action_err``: MSE of the predicted (normalised) action, the arg-max centre plus its offset;
        ``ce`` / ``centre_acc`` / ``offset``: the centre classifier and the true centre's offset; ``cot``: the
        CoT prediction of the last window index; ``bc``: the BC loss terms at that index."""
        cot_last = None
        if self.cot_head is not None:
            _, cot_pred = self._features(batch, train=False)
            cot_last = cot_pred[:, -1]
        return self._last_metrics(self._last_features(batch), batch, cot_last)

    def _last_metrics(self, feats: dict, batch: dict, cot_last: torch.Tensor | None) -> dict[str, torch.Tensor]:
        cfg = self.cfg
        target = self._chunk_targets(batch)[:, -1]  # (B, k, p): the chunk predicted at the last index
        k = target.shape[1]
        out: dict[str, torch.Tensor] = {}
        if cfg.action_head == "mse":
            pred = self.action_decoder(feats[cfg.centre_from]).float().unflatten(-1, (k, -1))
            out["bc"] = ((pred - target) ** 2).mean()
        elif cfg.action_head == "gmm":
            raw = self.mixture_head(feats[cfg.centre_from]).unflatten(-1, (k, -1))
            out["bc"] = self.mixture_nll(raw, target).mean()
            pred = self.mixture_mode(raw)
        else:
            logits = self.centre_head(feats[cfg.centre_from]).float().unflatten(-1, (k, -1))  # (B, k, K)
            true_c = self._nearest_centre(target)  # (B, k)
            off = self._true_centre_offsets(feats[cfg.offset_from], true_c).float()
            out["ce"] = F.cross_entropy(logits.flatten(0, 1), true_c.flatten())
            out["centre_acc"] = (logits.argmax(-1) == true_c).float().mean()
            out["offset"] = ((off - (target - self.centres[true_c])) ** 2).mean()
            out["bc"] = out["ce"] + cfg.offset_weight * out["offset"]
            c = logits.argmax(-1)  # what predict() outputs, from the same features
            pred = self.centres[c] + self._true_centre_offsets(feats[cfg.offset_from], c).float()
        out["action_err"] = ((pred - target) ** 2).mean()
        if cot_last is not None:
            out["cot"] = ((cot_last.float() - batch["cot"][:, -1]) ** 2).mean()
        return out

    @torch.no_grad()  # the inference path writes into preallocated buffers: no autograd through it
    def predict(self, batch: dict) -> torch.Tensor:
        """Normalised action (B, p) for the last window index (no random CoT mask): the first of its chunk."""
        return self._act(self._last_features(batch))[:, 0]

    @torch.no_grad()
    def predict_window(self, states, actions, timesteps, n_prev=None) -> torch.Tensor:
        """:meth:`predict` from the window's tensors (see :meth:`_infer_features`)."""
        return self.predict_window_chunk(states, actions, timesteps, n_prev)[:, 0]

    @torch.no_grad()
    def predict_window_chunk(self, states, actions, timesteps, n_prev=None) -> torch.Tensor:
        """The chunk (B, k, p) predicted at the last window index, a(t) .. a(t+k-1) (k = ``action_chunk``, 1 for
        the paper's policies); what ``select_action`` calls."""
        return self._act(self._infer_features(states, actions, timesteps, n_prev=n_prev))

    def _act(self, feats: dict) -> torch.Tensor:
        """The action heads at inference, (B, k, p): the MSE decoder; the gmm head's most likely mean (or the
        mixture mean, or a drawn mode's mean); the arg-max centre plus that centre's offset (or the expected
        action, or a drawn centre plus its offset), per chunk step."""
        cfg, k, p = self.cfg, self.cfg.action_chunk, self.action_dim
        if cfg.action_head == "mse":
            return run_mlp(self.action_decoder, feats[cfg.centre_from]).float().unflatten(-1, (k, p))
        if cfg.action_head == "gmm":
            raw = run_mlp(self.mixture_head, feats[cfg.centre_from]).unflatten(-1, (k, -1))
            if cfg.action_rule == "sample":
                logits, means, _ = self.mixture(raw)  # (B, k, M), (B, k, M, p)
                mode = self.draw_mode(logits.flatten(0, 1)).view(*logits.shape[:2], 1, 1).expand(-1, -1, 1, p)
                return means.gather(2, mode)[:, :, 0]
            return self.mixture_mean(raw) if cfg.action_rule == "mean" else self.mixture_mode(raw)
        if cfg.action_rule == "mean":  # every centre's offset, weighted by the classifier's probabilities
            probs = run_mlp(self.centre_head, feats[cfg.centre_from]).float().unflatten(-1, (k, -1)).softmax(-1)
            off = run_mlp(self.offset_head, feats[cfg.offset_from]).float().view(*probs.shape, p)  # (B, k, K, p)
            return ((self.centres + off) * probs[..., None]).sum(-2)
        logits = run_mlp(self.centre_head, feats[cfg.centre_from]).float().unflatten(-1, (k, -1))  # (B, k, K)
        if cfg.action_rule == "sample":  # BeT's own rule
            c = self.draw_mode(logits.flatten(0, 1)).view(logits.shape[:2])
        else:
            c = logits.argmax(-1)  # (B, k)
        # the offsets of centres c only (RowGatheredLinear's forward without the autograd bookkeeping)
        hidden = run_mlp(self.offset_head, feats[cfg.offset_from], n_layers=len(self.offset_head) - 1).float()
        last = self.offset_head[-1]
        rows = c + cfg.n_centres * torch.arange(k, device=c.device)  # chunk step j's group of K
        w = last.weight.view(-1, p, last.weight.shape[1])[rows.flatten()]  # (B k, p, h)
        x = hidden[:, None].expand(-1, k, -1).reshape(-1, hidden.shape[-1], 1)  # (B k, h, 1)
        off = torch.bmm(w, x)[:, :, 0].view(*c.shape, p) + last.bias.view(-1, p)[rows]
        return self.centres[c] + off


def _init_weights(m: nn.Module) -> None:
    # GPT-2 / minGPT initialisation, as in the official CoTPC code
    if isinstance(m, (nn.Linear, nn.Embedding)):
        nn.init.normal_(m.weight, std=0.02)
        if isinstance(m, nn.Linear) and m.bias is not None:
            nn.init.zeros_(m.bias)
    elif isinstance(m, GPT):
        if m.cot_tokens is not None:
            nn.init.normal_(m.cot_tokens, std=0.02)


register_family("transformer", TransformerConfig, TransformerPolicy, presets=TRANSFORMER_PRESETS)
