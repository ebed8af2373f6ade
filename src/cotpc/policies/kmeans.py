"""k-means of the (normalised) demo actions, BeT's action discretisation. Fitted once before training."""

from __future__ import annotations

import torch


def kmeans(x: torch.Tensor, k: int, iters: int = 50, seed: int = 0) -> torch.Tensor:
    """Lloyd's algorithm with k-means++ initialisation; returns (k, p) centres.

    Deterministic for a given seed. Empty clusters are re-seeded at the point farthest from its centre.
    """
    x = x.float()
    n = x.shape[0]
    if k > n:
        raise ValueError(f"k-means with {k} centres needs at least {k} actions, the data has {n}; lower n_centres")
    g = torch.Generator().manual_seed(seed)
    # k-means++: each new centre drawn with probability proportional to the squared distance to the nearest
    centres = x[torch.randint(n, (1,), generator=g)]
    d2 = ((x - centres[0]) ** 2).sum(-1)
    for _ in range(1, k):
        probs = d2 / d2.sum() if d2.sum() > 0 else torch.full_like(d2, 1.0 / n)
        c = x[torch.multinomial(probs, 1, generator=g)]
        centres = torch.cat([centres, c])
        d2 = torch.minimum(d2, ((x - c) ** 2).sum(-1))
    for _ in range(iters):
        assign = torch.cdist(x, centres).argmin(1)
        sums = torch.zeros_like(centres).index_add_(0, assign, x)
        counts = torch.bincount(assign, minlength=k).to(x.dtype)
        new = sums / counts.clamp_min(1)[:, None]
        empty = counts == 0
        if empty.any():
            far = ((x - centres[assign]) ** 2).sum(-1).topk(int(empty.sum())).indices
            new[empty] = x[far]
        if torch.allclose(new, centres):
            break
        centres = new
    return centres
