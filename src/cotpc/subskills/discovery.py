"""Exact unsupervised subskill discovery: segment an action sequence by minimising the paper's objective

    J(c_1..c_m) = sum_i [ C(a(c_{i-1}+1) .. a(c_i)) + beta ],   c_0 = -1, c_m = N-1
    C(v_1..v_n) = (1/n) sum_k d_cos(v_k, vbar),   vbar = mean of v,   d_cos(x, y) = 1 - x.y / (|x| |y|)

The paper uses PELT. PELT's pruning rule needs C(a..b) + C(b+1..c) <= C(a..c), which a *mean* cost does not
satisfy, so PELT can return a non-optimal segmentation (see `cotpc bench segment`). We instead run exact dynamic
programming over all O(N^2) segments, F[j] = min_i F[i] + C(i, j) + beta with F[0] = 0, in float64.

Why it is fast. With prefix sums PS of the actions v and PU of their unit vectors u, a segment (i, j] (actions
i..j-1) has S = PS_j - PS_i, U = PU_j - PU_i and n = j - i, and sum_k d_cos(v_k, S) = n - U.S / |S|, so

    C(i, j) = 1 - U.S / (n |S|).

|S|^2 and U.S expand into inner products of prefix-sum rows, so a whole block of the cost matrix is one batched
matrix product, and the DP recursion runs vectorised over a batch of trajectories (one small step per end
index j). Work is O(N^2 p) per trajectory, memory O(B * N * block) for a batch of B.

Zero-norm convention (no NaN, ever):
- an action is *zero* when |v| <= ZERO_ACTION_RTOL * max_k |v_k| over the trajectory; its unit vector is 0,
  so d_cos(0, y) = 1 for y != 0;
- a segment's mean is *zero* when |S| <= ZERO_MEAN_RTOL * sum_k |v_k| (its actions cancel out; for the fast
  path also when |S|^2 is below the float64 rounding noise of the prefix-sum expansion). Then
  d_cos(0, 0) = 0 and d_cos(x, 0) = 1, so C = (number of non-zero actions) / n: an all-zero segment costs 0.
- both are relative tolerances, so the result is invariant to scaling all actions by a positive factor.

Cost variants (``cost=``): "mean-cosine" is the paper's C above (the default everywhere). "sum-cosine" uses
n * C, the *total* cosine distance of the segment, so a segment's cost grows with its length like the classic
additive change-point costs. Under the mean cost one long noisy segment costs at most ~1 however long it is, so
noisy demos collapse to a single segment for any beta above the per-segment noise level (measured on Moving
Maze in docs/subskills.md); the sum cost does not have that failure. Everything else is shared.

Tie-breaking: when several predecessors i give the same F[j] (bit-for-bit), the smallest i wins, i.e. the
longest last segment. Float rounding of the prefix-sum formulation is ~1e-12 relative for typical inputs;
segmentations whose objectives differ by less than that are not distinguished.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch

from cotpc.data.targets import check_ends

ZERO_ACTION_RTOL = 1e-12  # |v| <= this * max |v| counts as a zero action
ZERO_MEAN_RTOL = 1e-6  # |sum v| <= this * sum |v| counts as a zero segment mean
_NOISE = 64 * np.finfo(np.float64).eps  # rounding noise of |S|^2 from the prefix-sum expansion (relative)
_BLOCK_ELEMS = 1 << 19  # elements per cost block: two float64 blocks (8 MB) stay in cache
_WIDTH = 16  # end indices per block: narrower wastes less of the rectangular block on unused i > j
COSTS = ("mean-cosine", "sum-cosine")


def check_actions(actions, where: str = "actions") -> np.ndarray:
    a = np.asarray(actions)
    if a.ndim != 2:
        raise ValueError(f"{where} must be a 2-D (N, p) array, got shape {a.shape}")
    if a.shape[0] == 0 or a.shape[1] == 0:
        raise ValueError(f"{where} is empty (shape {a.shape}); need N >= 1 actions of dimension p >= 1")
    if not np.issubdtype(a.dtype, np.number) or np.iscomplexobj(a):
        raise ValueError(f"{where} must be real numbers, got dtype {a.dtype}")
    a = a.astype(np.float64)
    if not np.all(np.isfinite(a)):
        bad = tuple(int(x) for x in np.argwhere(~np.isfinite(a))[0])
        raise ValueError(f"{where} holds NaN/inf (first at index {bad})")
    return a


def _check_params(beta: float, min_size: int, cost: str = COSTS[0]) -> tuple[float, int]:
    if cost not in COSTS:
        raise ValueError(f"cost must be one of {COSTS}, got {cost!r}")
    beta = float(beta)
    if not math.isfinite(beta) or beta < 0:
        raise ValueError(f"beta must be a finite number >= 0, got {beta}")
    if isinstance(min_size, bool) or int(min_size) != min_size or min_size < 1:
        raise ValueError(f"min_size must be an integer >= 1, got {min_size}")
    return beta, int(min_size)


def unit_actions(a: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit vectors (zero actions -> 0), norms, and the non-zero mask, following the zero convention."""
    norms = np.linalg.norm(a, axis=1)
    nonzero = norms > ZERO_ACTION_RTOL * norms.max()
    u = np.zeros_like(a)
    u[nonzero] = a[nonzero] / norms[nonzero, None]
    return u, norms, nonzero


def segment_cost(u: np.ndarray, v: np.ndarray, norms: np.ndarray, nonzero: np.ndarray) -> float:
    """C of one segment summed directly (the reference the fast path is checked against); ``u``, ``norms`` and
    ``nonzero`` come from :func:`unit_actions` over the whole trajectory, so "zero action" is decided trajectory-wide."""
    n = len(v)
    s = v.sum(axis=0)
    s_norm = float(np.linalg.norm(s))
    if s_norm <= ZERO_MEAN_RTOL * norms.sum():  # mean is zero: d(0, 0) = 0, d(x, 0) = 1
        return float(nonzero.sum()) / n
    # d_cos(v_k, vbar) = 1 - u_k . s / |s| (zero actions have u_k = 0, hence distance 1)
    return float(np.clip(np.mean(1.0 - u @ s / s_norm), 0.0, 2.0))


def objective(actions, ends, beta: float, cost: str = "mean-cosine") -> float:
    """J of the segmentation ``ends`` (inclusive end indices, strictly increasing, last = N-1).

    Computed segment by segment with direct sums (independent of the DP's prefix-sum expansion).
    """
    a = check_actions(actions)
    beta, _ = _check_params(beta, 1, cost)
    ends = check_ends(ends, len(a))
    u, norms, nonzero = unit_actions(a)
    total, start = 0.0, 0
    for e in ends:
        sl = slice(start, int(e) + 1)
        c = segment_cost(u[sl], a[sl], norms[sl], nonzero[sl])
        total += (c if cost == "mean-cosine" else c * (int(e) + 1 - start)) + beta
        start = int(e) + 1
    return total


def discover(actions, beta: float, min_size: int = 1, cost: str = "mean-cosine") -> np.ndarray:
    """Exact minimiser of J for one trajectory of (N, p) actions.

    Returns the inclusive segment end indices (int64, strictly increasing, last = N-1); every segment holds at
    least ``min_size`` actions. See the module docstring for the zero-norm convention, ``cost`` and tie-breaking.
    """
    return discover_batch([actions], beta, min_size, cost)[0]


def discover_batch(
    actions_list: Sequence, beta: float, min_size: int = 1, cost: str = "mean-cosine"
) -> list[np.ndarray]:
    """:func:`discover` for many trajectories at once (any lengths); same results, much faster.

    Trajectories are sorted by length and grouped, each group padded with zero actions to its longest member
    (padding sits after a trajectory's end, so it cannot change that trajectory's DP values).
    """
    beta, min_size = _check_params(beta, min_size, cost)
    arrays = [check_actions(a, f"actions[{k}]") for k, a in enumerate(actions_list)]
    for k, a in enumerate(arrays):
        if len(a) < min_size:
            raise ValueError(f"actions[{k}] has N = {len(a)} < min_size = {min_size} actions")
        if a.shape[1] != arrays[0].shape[1]:
            raise ValueError(f"actions[{k}] has dimension {a.shape[1]}, actions[0] has {arrays[0].shape[1]}")
    # Groups of (sorted) trajectories small enough for the memory budget at the group's longest length.
    order = sorted(range(len(arrays)), key=lambda k: len(arrays[k]))
    groups: list[list[int]] = []
    for k in order:
        if groups and (len(groups[-1]) + 1) * (len(arrays[k]) + 1) * _WIDTH <= _BLOCK_ELEMS:
            groups[-1].append(k)
        else:
            groups.append([k])

    def run(group: list[int]) -> list[np.ndarray]:
        return _dp_group([arrays[k] for k in group], len(arrays[group[-1]]), beta, min_size, cost == "sum-cosine")

    # One single-threaded worker per core, each on whole groups. Torch's own intra-op threads would have to meet
    # at a barrier after each of the thousands of small per-column ops: fine on an idle machine, but when another
    # process holds a core, every barrier waits for a scheduler slice and a 0.3 s job takes 20 s.
    workers = max(1, min(len(groups), torch.get_num_threads(), 8))  # beyond ~8 the GIL is the bottleneck
    prev = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        if workers == 1:
            results = [run(g) for g in groups]
        else:
            with ThreadPoolExecutor(workers) as pool:  # torch ops release the GIL
                results = list(pool.map(run, groups))
    finally:
        torch.set_num_threads(prev)
    out: list[np.ndarray] = [np.empty(0, dtype=np.int64)] * len(arrays)
    for group, ends in zip(groups, results):
        for k, e in zip(group, ends):
            out[k] = e
    return out


def _dp_group(arrays: list[np.ndarray], L: int, beta: float, min_size: int, summed: bool) -> list[np.ndarray]:
    B, p = len(arrays), arrays[0].shape[1]
    f64 = torch.float64
    lengths = np.array([len(a) for a in arrays])
    # Everything is laid out feature-major, (B, features, L+1): the cumulative sums run along contiguous memory
    # and the matrices fed to the batched product need no transposed copies.
    v_np = np.zeros((B, L, p))
    for b, a in enumerate(arrays):
        v_np[b, : len(a)] = a  # zero padding after each trajectory's end
    v = torch.from_numpy(v_np).transpose(1, 2).contiguous()  # (B, p, L)
    norms = (v * v).sum(dim=1).sqrt_()  # (B, L)
    nonzero = norms > ZERO_ACTION_RTOL * norms.amax(dim=1, keepdim=True)  # padding: 0 > 0 is False
    u = v / torch.where(nonzero, norms, 1.0)[:, None] * nonzero[:, None]

    def prefix(x):  # (..., L) -> (..., L+1) with a leading zero
        out = torch.zeros((*x.shape[:-1], L + 1), dtype=f64)
        torch.cumsum(x, dim=-1, out=out[..., 1:])
        return out

    # Centring the prefix sums (per trajectory, over its own N+1 entries) leaves every difference PS_j - PS_i
    # unchanged but shrinks the magnitudes that the inner-product expansion cancels, i.e. its rounding error.
    n1 = torch.from_numpy(lengths + 1).to(f64)[:, None, None]
    valid = torch.arange(L + 1)[None, None, :] < n1
    ps, pu = prefix(v), prefix(u)  # (B, p, L+1)
    ps -= (ps * valid).sum(dim=2, keepdim=True) / n1
    pu -= (pu * valid).sum(dim=2, keepdim=True) / n1
    pn, pz = prefix(norms), prefix(nonzero.to(f64))  # (B, L+1): prefix sums of |v| and of the non-zero count

    ss = (ps * ps).sum(dim=1)  # |PS_i|^2
    us = (pu * ps).sum(dim=1)  # PU_i . PS_i
    one = torch.ones((B, L + 1), dtype=f64)

    def stack(*parts):  # (B, k, L+1) / (B, L+1) parts -> (B, sum k, L+1)
        return torch.cat([x if x.dim() == 3 else x[:, None] for x in parts], dim=1)

    # Column i of X times column j of Y gives, for the segment (i, j]:
    #   |S|^2 = |PS_i|^2 + |PS_j|^2 - 2 PS_i.PS_j        U.S = PU_i.PS_i + PU_j.PS_j - PU_i.PS_j - PS_i.PU_j
    xs, ys = stack(ps, ss, one), stack(-2 * ps, one, ss)
    xu, yu = stack(pu, ps, us, one), stack(-ps, -pu, one, us)
    # Zero mean (the convention's branch) when |S|^2 <= tol^2 (PN_j - PN_i)^2 + noise (|PS_i|^2 + |PS_j|^2), the
    # last term covering the rounding of the expansion itself. The fast path below runs whenever every
    # candidate's |S|^2 exceeds this per-trajectory upper bound of the threshold (the usual case).
    t2, e = ZERO_MEAN_RTOL**2, _NOISE
    thr = t2 * pn[:, -1] ** 2 + 2 * e * ss.amax(dim=1)
    zm = (1 - e) * ss - t2 * pn**2
    zero_cols = lambda: (stack(ps, zm, one, pn), stack(-2 * ps, one, zm, 2 * t2 * pn))  # noqa: E731
    xz = yz = None  # X_i . Y_j = |S|^2 - threshold (<= 0: zero mean); built only if needed

    inv_n = 1.0 / torch.arange(L, 0, -1, dtype=f64)  # inv_n[L - j + i] = 1 / (j - i)
    # F[i] = best J of actions 0..i-1 (F[0] = 0). We store H[i] = F[i] + off[i] with off = 1 (mean cost) or -i
    # (sum cost), which turns F[i] + cost(i, j) into H[i] - U.S / (n |S|), resp. H[i] - U.S / |S| + j.
    off = -torch.arange(L + 1, dtype=f64) if summed else torch.ones(L + 1, dtype=f64)
    H = torch.full((B, L + 1), math.inf, dtype=f64)
    H[:, 0] = off[0]
    arg = torch.zeros((B, L + 1), dtype=torch.int64)
    width = max(1, min(_WIDTH, _BLOCK_ELEMS // (B * (L + 1))))
    # Scratch buffers reused by every block and column: fresh multi-MB allocations would be page-faulted in on
    # each call (glibc maps large blocks anew), which doubled the time of a first call.
    buf_s2, buf_dot = torch.empty(B * width * L, dtype=f64), torch.empty(B * width * L, dtype=f64)
    buf_cand = torch.empty(B * L, dtype=f64)
    for j0 in range(min_size, L + 1, width):
        j1 = min(L + 1, j0 + width)
        rows = j1 - min_size  # predecessors i <= j - min_size
        # (B, w, rows) blocks: entry [b, j - j0, i] is the quantity for segment (i, j]
        shape = (B, j1 - j0, rows)
        s2 = torch.bmm(ys[:, :, j0:j1].transpose(1, 2), xs[:, :, :rows], out=buf_s2[: math.prod(shape)].view(shape))
        dot = torch.bmm(yu[:, :, j0:j1].transpose(1, 2), xu[:, :, :rows], out=buf_dot[: math.prod(shape)].view(shape))
        # the last `width` predecessors include i > j - min_size (even i = j, |S| = 0): keep them out of the check
        tri = torch.arange(rows - (j1 - j0), rows)[None, :] > torch.arange(j0, j1)[:, None] - min_size
        s2[:, :, rows - (j1 - j0) :].masked_fill_(tri, math.inf)
        if bool((s2.amin(dim=(1, 2)) > thr).all()):  # fast path: no zero means in this block
            q = s2.rsqrt_().mul_(dot)  # U.S / |S|
            for j in range(j0, j1):
                r, w = j - min_size + 1, j - j0
                cand = buf_cand[: B * r].view(B, r)
                if summed:
                    torch.sub(H[:, :r], q[:, w, :r], out=cand)
                else:
                    torch.addcmul(H[:, :r], q[:, w, :r], inv_n[L - j : L - j + r], value=-1.0, out=cand)
                torch.min(cand, dim=1, out=(H[:, j], arg[:, j]))  # first minimum -> smallest i on exact ties
                H[:, j] += beta + (0.0 if summed else 1.0)  # F[j] + off[j]
            continue
        if xz is None:
            xz, yz = zero_cols()
        for j in range(j0, j1):  # some segment may have a zero mean: apply the convention where it does
            r, w = j - min_size + 1, j - j0
            inv = inv_n[L - j : L - j + r]
            zero = torch.bmm(yz[:, :, j : j + 1].transpose(1, 2), xz[:, :, :r])[:, 0] <= 0
            cost = (1.0 - dot[:, w, :r] * torch.rsqrt(s2[:, w, :r].clamp_min(1e-300)) * inv).clamp_(0.0, 2.0)
            cost = torch.where(zero, (pz[:, j : j + 1] - pz[:, :r]) * inv, cost)  # C = nnz / n
            if summed:
                cost = cost / inv  # n C
            best, idx = torch.min(H[:, :r] - off[:r] + cost, dim=1)
            H[:, j] = best + beta + off[j]
            arg[:, j] = idx
    # backtrack all trajectories together: follow arg from each trajectory's own end N, marking segment ends
    arg = arg.numpy()
    is_end = np.zeros((B, L), dtype=bool)
    cur = lengths.copy()
    while (active := cur > 0).any():
        is_end[np.flatnonzero(active), cur[active] - 1] = True
        cur = np.where(active, arg[np.arange(B), cur], cur)
    return [np.flatnonzero(is_end[b]).astype(np.int64) for b in range(B)]
