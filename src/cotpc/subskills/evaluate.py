"""How well discovered subskill boundaries recover privileged key steps (Moving Maze region entries).

Both sides are *state* indices: a discovered segment ending at action ``c_i`` gives the boundary state
``c_i + 1`` (see :mod:`cotpc.data.targets`), and ``key_steps`` are the first states inside each new region.
The final state ``N`` (end of the last segment) is not a boundary: every segmentation has it.

A predicted boundary matches a true one when they are at most ``tol`` steps apart, one-to-one (maximum matching;
for points on a line with a tolerance, the greedy left-to-right sweep is optimal). Precision and recall are
micro-averaged over demos: matched / predicted and matched / true, summed over all demos.
"""

from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np

from cotpc.subskills.discovery import discover_batch


def boundaries(ends: np.ndarray) -> np.ndarray:
    """Internal boundary state indices of a segmentation: ``c_i + 1`` for all but the last segment."""
    return np.asarray(ends, dtype=np.int64)[:-1] + 1


def count_matches(pred: np.ndarray, true: np.ndarray, tol: int) -> int:
    """Size of a maximum one-to-one matching between sorted ``pred`` and ``true`` with |p - t| <= tol."""
    pred, true = np.sort(pred), np.sort(true)
    i = k = matched = 0
    while i < len(pred) and k < len(true):
        if abs(int(pred[i]) - int(true[k])) <= tol:
            matched, i, k = matched + 1, i + 1, k + 1
        elif pred[i] < true[k]:
            i += 1
        else:
            k += 1
    return matched


def score(ends_list: Sequence[np.ndarray], key_steps: Sequence[np.ndarray] | None, tol: int = 2) -> dict:
    """Segmentation statistics, plus precision / recall / F1 against ``key_steps`` when given."""
    counts = np.array([len(e) for e in ends_list])
    lengths = np.concatenate([np.diff(np.concatenate([[-1], e])) for e in ends_list])
    out = {
        "demos": len(ends_list),
        "subskills_mean": float(counts.mean()),
        "subskills_min": int(counts.min()),
        "subskills_max": int(counts.max()),
        "length_mean": float(lengths.mean()),
        "length_min": int(lengths.min()),
        "length_max": int(lengths.max()),
    }
    if key_steps is not None:
        matched = n_pred = n_true = 0
        for e, k in zip(ends_list, key_steps):
            b, k = boundaries(e), np.asarray(k, dtype=np.int64)
            matched += count_matches(b, k, tol)
            n_pred, n_true = n_pred + len(b), n_true + len(k)
        p = matched / n_pred if n_pred else 0.0
        r = matched / n_true if n_true else 0.0
        out.update(tol=tol, matched=matched, predicted=n_pred, true=n_true, precision=p, recall=r,
                   f1=2 * p * r / (p + r) if p + r else 0.0)
        if len({len(k) for k in key_steps}) == 1:  # same key steps in every demo: which ones are found
            hits = [[bool(np.any(np.abs(boundaries(e) - t) <= tol)) for t in k] for e, k in zip(ends_list, key_steps)]
            out["recall_per_key"] = np.mean(hits, axis=0).tolist()  # (not one-to-one: a diagnostic)
    return out


def sweep(actions: Sequence[np.ndarray], key_steps: Sequence[np.ndarray] | None, betas: Sequence[float],
          min_size: int = 1, tol: int = 2, cost: str = "mean-cosine") -> list[dict]:
    """:func:`score` of the exact segmentation for each beta (one row per beta, with the seconds it took)."""
    rows = []
    for beta in betas:
        t0 = time.perf_counter()
        ends = discover_batch(actions, beta, min_size, cost)
        seconds = time.perf_counter() - t0
        rows.append({"cost": cost, "beta": float(beta), "seconds": seconds, **score(ends, key_steps, tol)})
    return rows


def sweep_table(rows: list[dict]) -> str:
    """Markdown table of :func:`sweep` rows."""
    has_keys = "precision" in rows[0]
    head = "| beta | subskills / demo (mean, min-max) | segment length (mean) |"
    head += " precision | recall | F1 |" if has_keys else ""
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        line = (f"| {r['beta']:g} | {r['subskills_mean']:.2f} ({r['subskills_min']}-{r['subskills_max']}) "
                f"| {r['length_mean']:.1f} |")
        if has_keys:
            line += f" {r['precision']:.3f} | {r['recall']:.3f} | {r['f1']:.3f} |"
        lines.append(line)
    return "\n".join(lines)
