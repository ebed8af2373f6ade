"""The one GPT backbone: token layout, attention mask, pre-LN blocks (nanoGPT style).

A window of T timesteps ending at time t is laid out as

    [cot_0 .. cot_{C-1}], s(t-T+1), a(t-T+1), ..., s(t-1), a(t-1), s(t)          (C + 2T - 1 tokens)

(without the action tokens when ``use_actions`` is False). Window index i = 0..T-1 stands for timestep
t-T+1+i. Who may attend to whom is decided by :func:`build_mask` from this layout alone:

- CoT tokens are all-to-all (they see every token, including each other);
- state/action tokens are causal (an earlier or the same token) and see all CoT tokens;
- training only: CoT tokens do not see state/action tokens of window index i > T-1-l (timesteps t' > t-l),
  with l drawn per sample;
- or, with ``causal_cot`` (the leak-free design), CoT token j sits at window index j: every token has a time
  (s(i) and cot_i: 2i, a(i): 2i + 1) and sees exactly the tokens of an earlier or equal time, so what predicts
  the action of index i never saw a(>=i) or s(>i), through any number of blocks (no random mask needed);
- windows that start before the episode are left-padded; padded tokens are hidden from everyone (each token
  still sees itself, so no softmax row is empty and nothing turns NaN).

Attention runs ``F.scaled_dot_product_attention`` on CUDA (fused kernels) and :class:`MaskedAttention`, a plain
matmul + masked softmax with a hand-written backward, on a CPU: for our small heads (29 tokens x 16 dims) the CPU
SDPA kernels are slower (measured in docs/performance.md), and their bf16 backward especially so. Long windows
(``LONG_WINDOW`` tokens or more, e.g. the official code's ManiSkill context of 60) go to SDPA's flash kernel in fp32.

Inference (``select_action``) runs :meth:`GPT.infer`: the same maths in fewer ops (no autograd bookkeeping, a
looked-up padding mask, the last block on the tokens read only); at batch 1 a step is ~150 small ops, and on a
CPU the op count and the weights streamed through the cache cost more than the arithmetic.
"""

from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

from cotpc.policies.base import mlp
from cotpc.policies.transformer.config import TransformerConfig


class Layout:
    """Token positions of a window: which token is a CoT, state or action token, and its window index."""

    def __init__(self, context: int, n_cot: int, use_actions: bool, causal_cot: bool = False):
        self.T, self.C, self.use_actions, self.causal_cot = context, n_cot, use_actions, causal_cot
        T, C = context, n_cot
        stride = 2 if use_actions else 1
        self.state_pos = torch.arange(T) * stride + C  # token index of s(i)
        self.action_pos = torch.arange(T - 1) * 2 + C + 1 if use_actions else torch.zeros(0, dtype=torch.long)
        self.length = C + (2 * T - 1 if use_actions else T)
        kind = torch.zeros(self.length, dtype=torch.long)  # 0 cot, 1 state, 2 action
        step = torch.full((self.length,), -1, dtype=torch.long)  # window index (-1 for CoT tokens)
        kind[self.state_pos] = 1
        step[self.state_pos] = torch.arange(T)
        if use_actions:
            kind[self.action_pos] = 2
            step[self.action_pos] = torch.arange(T - 1)
        self.kind, self.step = kind, step
        # time order of the causal-CoT design: s(i) and cot_i at i * stride, a(i) right after s(i); a single CoT
        # token (vanilla) sits at the last index
        time = torch.zeros(self.length, dtype=torch.long)
        time[self.state_pos] = torch.arange(T) * stride
        if use_actions:
            time[self.action_pos] = torch.arange(T - 1) * 2 + 1
        time[:C] = (torch.arange(C) + T - C) * stride
        self.time = time


def build_mask(layout: Layout, valid: torch.Tensor | None = None, cot_hide: torch.Tensor | None = None) -> torch.Tensor:
    """Boolean attention mask, True = may attend: (L, L) without per-sample parts, else (B, 1, L, L).

    Args:
        layout: the token layout.
        valid: (B, T) bool, False for left-padding window indices (before the episode start).
        cot_hide: (B,) long, the drawn l: CoT tokens do not see window indices i > T-1-l.
    """
    L, T = layout.length, layout.T
    is_cot = layout.kind == 0
    pos = torch.arange(L)
    if layout.causal_cot:  # every token sees the tokens of an earlier or equal time; nothing to hide at random
        mask, cot_hide = layout.time[None, :] <= layout.time[:, None], None
    else:  # causal among state/action tokens, and everyone sees the CoT tokens; CoT tokens see everything
        mask = (pos[None, :] <= pos[:, None]) | is_cot[None, :] | is_cot[:, None]
    if valid is None and cot_hide is None:
        return mask
    B = (valid if valid is not None else cot_hide).shape[0]
    device = (valid if valid is not None else cot_hide).device
    mask = mask.to(device).expand(B, L, L).clone()
    step = layout.step.to(device)
    key_step = step.clamp(min=0)[None, :].expand(B, L)  # (B, L)
    if cot_hide is not None:
        hidden = (step[None, :] >= 0) & (key_step > (T - 1 - cot_hide)[:, None])  # (B, L) keys hidden from CoT
        mask[:, is_cot.to(device), :] &= ~hidden[:, None, :]
    if valid is not None:
        key_ok = torch.gather(valid, 1, key_step) | (step[None, :] < 0)  # (B, L)
        mask &= key_ok[:, None, :]
        mask |= torch.eye(L, dtype=torch.bool, device=device)  # a padded query sees itself: no empty row
    return mask[:, None]


def _dropout(p: float) -> nn.Module:
    """Dropout, or nothing at p = 0 (the default): a p = 0 dropout in training mode still costs a pass over
    its input, and on a CPU with little memory bandwidth each pass over a (B, L, d) activation shows."""
    return nn.Dropout(p) if p > 0 else nn.Identity()


class MaskedAttention(torch.autograd.Function):
    """softmax(q k^T / sqrt(d) + bias) v for (B, H, L, d) tensors, with an additive (B or 1, 1, L, L) bias.

    Exact (the same maths as SDPA; tested against it on values and gradients). Why a hand-written backward: the
    autograd graph of the same expression hands CPU ``bmm`` non-contiguous batched operands, which it then
    copies matrix by matrix (~12K small copies per step). Scores and softmax are in fp32 even when q, k, v are
    bf16, so bf16 loses nothing in the softmax.
    """

    @staticmethod
    def forward(ctx, q, k, v, bias):
        q, k, v = q.contiguous(), k.contiguous(), v.contiguous()
        scale = q.shape[-1] ** -0.5
        with torch.autocast(q.device.type, enabled=False):
            scores = torch.matmul(q, k.transpose(-1, -2)).float().mul_(scale).add_(bias)
            p = torch.softmax(scores, dim=-1)
            y = torch.matmul(p.to(v.dtype), v)
        ctx.save_for_backward(q, k, v, p)
        ctx.scale = scale
        return y

    @staticmethod
    def backward(ctx, dy):
        q, k, v, p = ctx.saved_tensors
        dy = dy.contiguous().to(v.dtype)
        with torch.autocast(q.device.type, enabled=False):
            pv = p.to(v.dtype)
            dv = torch.matmul(pv.transpose(-1, -2), dy)
            dp = torch.matmul(dy, v.transpose(-1, -2)).float()
            ds = (dp - (dp * p).sum(-1, keepdim=True)).mul_(p).mul_(ctx.scale).to(q.dtype)
            dq = torch.matmul(ds, k)
            dk = torch.matmul(ds.transpose(-1, -2), q)
        return dq, dk, dv, None


def mask_to_bias(mask: torch.Tensor) -> torch.Tensor:
    """Boolean attention mask (True = may attend) -> additive fp32 bias (0 or -inf), shaped (B or 1, 1, L, L)."""
    bias = torch.zeros(mask.shape, dtype=torch.float32, device=mask.device).masked_fill_(~mask, float("-inf"))
    return bias.view(-1, 1, *mask.shape[-2:])


# From this many keys on, a CPU trains faster with SDPA's flash kernel in fp32 than with MaskedAttention: the
# (B, H, L, L) scores and probabilities MaskedAttention keeps outgrow the caches, and each of its passes over
# them waits on memory, while the flash kernel works tile by tile and never stores them. Measured on one core of
# a Zen 4 EPYC (docs/performance.md, "Long windows"): MaskedAttention in bf16 is faster up to ~90 tokens
# (our contexts of 10-20: 29-59 tokens), the flash kernel from ~120 (the official code's ManiSkill context of
# 60: 119 tokens for BeT and DT, 179 for CoTPC; 2-3x faster there).
LONG_WINDOW = 100


def attention(q, k, v, mask: torch.Tensor, bias: torch.Tensor | None, dropout_p: float) -> torch.Tensor:
    """Masked multi-head attention: fused SDPA on CUDA (or with attention dropout); on a CPU
    :class:`MaskedAttention` for short windows and SDPA's flash kernel in fp32 for long ones (``LONG_WINDOW``
    keys or more; in fp32 because its bf16 backward is slow on a CPU). ``bias`` is ``mask_to_bias(mask)``
    (computed once per forward pass, shared by the blocks). The choice depends on shapes only, so a resumed run
    takes the same kernels."""
    if q.device.type == "cuda" or dropout_p > 0 or bias is None:
        return F.scaled_dot_product_attention(q, k, v, attn_mask=mask, dropout_p=dropout_p)
    if k.shape[-2] >= LONG_WINDOW:
        with torch.autocast(q.device.type, enabled=False):
            y = F.scaled_dot_product_attention(q.float(), k.float(), v.float(), attn_mask=mask)
        return y.to(q.dtype)
    return MaskedAttention.apply(q, k, v, bias)


def infer_attention(q, k, v, bias: torch.Tensor, n_heads: int) -> torch.Tensor:
    """Inference-only :func:`attention` (no autograd, no dropout) on heads flattened into the batch: q (B*H, R, d),
    k and v (B*H, L, d), the additive bias (B or 1, 1, R, L). The maths of :class:`MaskedAttention` (scale and
    bias in the scores' GEMM call: ``baddbmm``) without its bookkeeping (the ``autograd.Function`` call, the
    contiguous copies, the saved tensors), which at batch 1 costs more than the arithmetic."""
    BH, R, d = q.shape
    if bias.shape[0] == 1:
        bias = bias[0]  # (1, R, L): broadcast over the batch and the heads
    else:
        bias = bias.expand(-1, n_heads, -1, -1).reshape(BH, R, -1)
    scores = torch.baddbmm(bias, q, k.transpose(1, 2), alpha=d ** -0.5)
    return torch.bmm(torch.softmax(scores, dim=-1), v)


class Block(nn.Module):
    """Pre-LN transformer block with fused QKV and :func:`attention`."""

    def __init__(self, d: int, n_heads: int, dropout: float):
        super().__init__()
        self.n_heads, self.dropout = n_heads, dropout
        self.ln1, self.ln2 = nn.LayerNorm(d), nn.LayerNorm(d)
        self.qkv = nn.Linear(d, 3 * d)
        self.proj = nn.Linear(d, d)
        self.mlp = nn.Sequential(nn.Linear(d, 4 * d), nn.GELU(), nn.Linear(4 * d, d), _dropout(dropout))
        self.resid_drop = _dropout(dropout)

    def forward(self, x: torch.Tensor, mask: torch.Tensor, bias: torch.Tensor | None = None,
                rows: torch.Tensor | None = None) -> torch.Tensor:
        """``rows``: compute the output of these token positions only (every token is still attended to)."""
        B, L, D = x.shape
        H = self.n_heads
        q, k, v = self.qkv(self.ln1(x)).view(B, L, 3, H, D // H).permute(2, 0, 3, 1, 4)
        if rows is not None:  # the heads read a few tokens of the last block only
            q, x, mask = q[:, :, rows], x[:, rows], mask[..., rows, :]
            bias = bias[..., rows, :] if bias is not None else None
        y = attention(q, k, v, mask, bias, self.dropout if self.training else 0.0)
        x = x + self.resid_drop(self.proj(y.transpose(1, 2).reshape(B, x.shape[1], D)))
        return x + self.mlp(self.ln2(x))

    def infer(self, x: torch.Tensor, bias: torch.Tensor, rows=None) -> torch.Tensor:
        """Inference-only :meth:`forward` (eval mode: no dropout): the same maths with the layers' functions
        called directly, and :func:`infer_attention`. ``bias`` is the additive mask (B or 1, 1, L, L); ``rows``
        (token positions, a tensor or a slice) as in :meth:`forward`."""
        B, L, D = x.shape
        H, d = self.n_heads, D // self.n_heads
        h = F.layer_norm(x, (D,), self.ln1.weight, self.ln1.bias, self.ln1.eps)
        qkv = F.linear(h, self.qkv.weight, self.qkv.bias).view(B, L, 3, H, d).permute(2, 0, 3, 1, 4)
        q, k, v = qkv.reshape(3, B * H, L, d)  # a view at batch 1
        if rows is not None:
            q, x, bias = q[:, rows], x[:, rows], bias[..., rows, :]
        R = x.shape[1]
        y = infer_attention(q, k, v, bias, H).view(B, H, R, d).transpose(1, 2).reshape(B, R, D)
        x = x + F.linear(y, self.proj.weight, self.proj.bias)
        fc1, act, fc2 = self.mlp[0], self.mlp[1], self.mlp[2]
        h = F.layer_norm(x, (D,), self.ln2.weight, self.ln2.bias, self.ln2.eps)
        return x + F.linear(F.gelu(F.linear(h, fc1.weight, fc1.bias), approximate=act.approximate),
                            fc2.weight, fc2.bias)


class GPT(nn.Module):
    """Encoders, positional embeddings, CoT prompt tokens and the blocks. Returns token features."""

    def __init__(self, cfg: TransformerConfig, state_dim: int, action_dim: int, max_timestep: int, n_cot: int):
        super().__init__()
        d = cfg.d_model
        self.cfg, self.max_timestep = cfg, max_timestep
        self.layout = Layout(cfg.context, n_cot, cfg.use_actions, causal_cot=cfg.cot_attention == "causal")
        self.state_enc = mlp([state_dim, cfg.hidden, d])
        self.action_enc = mlp([action_dim, cfg.hidden, d]) if cfg.use_actions else None
        self.cot_tokens = nn.Parameter(torch.zeros(n_cot, d)) if n_cot else None  # no positional embedding
        # episode timestep, DT style (cfg.episode_timestep False: only the index in the window)
        self.global_emb = nn.Embedding(max_timestep, d) if cfg.episode_timestep else None
        self.local_emb = nn.Parameter(torch.zeros(cfg.context, d))  # index in the window
        self.drop = _dropout(cfg.dropout)
        self.blocks = nn.ModuleList([Block(d, cfg.n_heads, cfg.dropout) for _ in range(cfg.n_layers)])
        self.ln_f = nn.LayerNorm(d)
        # the inference mask never changes: build it once (buffers follow .to(device), not saved)
        self.register_buffer("base_mask", build_mask(self.layout), persistent=False)
        self.register_buffer("base_bias", mask_to_bias(self.base_mask), persistent=False)
        # inference: the bias of a window that starts n = 0..T-1 steps before its last index (left padding
        # before that), so select_action looks it up instead of building it each step
        T = cfg.context
        starts = torch.arange(T)[None, :] >= (T - 1 - torch.arange(T))[:, None]  # (n, window index)
        self.register_buffer("padded_bias", mask_to_bias(build_mask(self.layout, starts)), persistent=False)

    def forward(
        self,
        states: torch.Tensor,
        actions: torch.Tensor | None,
        timesteps: torch.Tensor,
        valid: torch.Tensor | None = None,
        cot_hide: torch.Tensor | None = None,
        keep_layer: int | None = None,
        rows: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """states (B,T,q) normalised, actions (B,T-1,p) normalised, timesteps (B,T) long.

        Returns the final LayerNorm'd features (B, L, d) and, if ``keep_layer`` is set, the raw output of that
        block (for the CoT decoder). With ``rows`` (token positions) the last block computes only those tokens
        and the features are (B, len(rows), d): the heads read only some tokens (in training the state and CoT
        tokens, at inference two or three), so the last block computes only those.
        """
        B, T, _ = states.shape
        lay = self.layout
        pos = self.positions(timesteps)  # (B, T, d)
        s = self.state_enc(states) + pos
        parts = []
        if lay.C:
            parts.append(self.cot_tokens.expand(B, -1, -1))
        if lay.use_actions:
            a = self.action_enc(actions) + pos[:, :-1]
            sa = torch.stack([s[:, :-1], a], dim=2).reshape(B, 2 * (T - 1), s.shape[-1])  # s0 a0 s1 a1 ... (none if T=1)
            parts += [sa, s[:, -1:]]
        else:
            parts.append(s)
        x = self.drop(torch.cat(parts, dim=1) if len(parts) > 1 else parts[0])
        if valid is None and cot_hide is None:
            mask, bias = self.base_mask, self.base_bias
        else:
            mask = build_mask(lay, valid, cot_hide if lay.C else None)
            bias = mask_to_bias(mask) if mask.device.type != "cuda" else None  # CUDA: SDPA takes the mask
        kept = None
        last = len(self.blocks) - 1
        for j, block in enumerate(self.blocks):
            x = block(x, mask, bias, rows if j == last else None)
            if j == keep_layer:
                kept = x
        return self.ln_f(x), kept

    # --- inference only (eval mode, no autograd): the same values as forward(), in fewer and cheaper ops ---
    def inference_bias(self, valid: torch.Tensor | None = None, n_prev: torch.Tensor | None = None) -> torch.Tensor:
        """Additive mask (B or 1, 1, L, L) of windows with left padding given as ``valid`` (B, T) bool or as
        ``n_prev`` (B,) long, the number of earlier steps each window holds (>= T - 1: none padded)."""
        if n_prev is not None:
            return self.padded_bias[n_prev.clamp(max=self.layout.T - 1)]
        if valid is not None:
            return mask_to_bias(build_mask(self.layout, valid))
        return self.base_bias

    def positions(self, timesteps: torch.Tensor) -> torch.Tensor:
        """(B, T, d): each token's position, the episode timestep's embedding (clamped to the longest training
        demo, so steps past it share its row) plus the index in the window; the index alone without
        ``episode_timestep``."""
        if self.global_emb is None:
            return self.local_emb.expand(timesteps.shape[0], -1, -1)
        return F.embedding(timesteps.clamp(0, self.max_timestep - 1), self.global_emb.weight) + self.local_emb

    def embed(self, states: torch.Tensor, actions: torch.Tensor | None, timesteps: torch.Tensor) -> torch.Tensor:
        """The input tokens (B, L, d) of :meth:`forward`, written into one buffer (no stack and cat). Slice
        assignment rather than ``torch.add(..., out=strided view)``: the same speed eager, and ``torch.compile``
        traces it as one graph (an ``out=`` into a non-contiguous view breaks the graph)."""
        B, T, _ = states.shape
        lay = self.layout
        C = lay.C
        pos = self.positions(timesteps)
        x = torch.empty(B, lay.length, pos.shape[-1], dtype=pos.dtype, device=pos.device)
        if C:
            x[:, :C] = self.cot_tokens
        if lay.use_actions:  # s0 a0 s1 a1 ... s(T-1): states at every second token, actions in between
            x[:, C::2] = run_mlp(self.state_enc, states) + pos
            if T > 1:
                x[:, C + 1::2] = run_mlp(self.action_enc, actions) + pos[:, :-1]
        else:
            x[:, C:] = run_mlp(self.state_enc, states) + pos
        return x

    def infer(self, states: torch.Tensor, actions: torch.Tensor | None, timesteps: torch.Tensor, bias: torch.Tensor,
              rows=None, n_blocks: int | None = None) -> torch.Tensor:
        """The raw output (no final LayerNorm) of block ``n_blocks - 1`` (default: the last) at token positions
        ``rows`` (a tensor or a slice; None: all), computing only those tokens in that block. ``bias`` from
        :meth:`inference_bias`."""
        x = self.embed(states, actions, timesteps)
        n = len(self.blocks) if n_blocks is None else n_blocks  # (slicing a ModuleList builds a new one)
        for j in range(n):
            x = self.blocks[j].infer(x, bias, rows if j == n - 1 else None)
        return x


def run_mlp(seq: nn.Sequential, x: torch.Tensor, n_layers: int | None = None) -> torch.Tensor:
    """``seq[:n_layers](x)`` for an :func:`mlp`, calling the functions of its Linear and ReLU layers directly (at
    batch 1 the module-call overhead is a visible part of each layer's cost; slicing a Sequential builds one)."""
    for i, m in enumerate(seq):
        if i == n_layers:
            break
        if isinstance(m, nn.Linear):
            x = F.linear(x, m.weight, m.bias)
        else:
            x = F.relu(x) if isinstance(m, nn.ReLU) else m(x)
    return x
