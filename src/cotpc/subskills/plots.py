"""Figures for subskill discovery (matplotlib, Agg backend): action similarity maps with the discovered
boundaries (the paper's Fig. 3) and the beta sweep. A task's own figures (the maze's paths coloured by
subskill) live with the task's demos and are found through its suite (cotpc.studies.suites)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from cotpc.subskills.discovery import unit_actions  # noqa: E402
from cotpc.data.targets import key_state_indices  # noqa: E402


def cosine_similarity_map(actions: np.ndarray) -> np.ndarray:
    """(N, N) pairwise cosine similarity of the actions; a zero action has similarity 0 to everything."""
    u, _, _ = unit_actions(np.asarray(actions, dtype=np.float64))
    return u @ u.T


def plot_similarity_maps(out: Path, actions_list, ends_list, titles, key_steps_list=None) -> Path:
    """One panel per demo: the action cosine-similarity map, discovered boundaries as white lines (and, if
    given, the privileged key steps as ticks on the axes)."""
    k = len(actions_list)
    fig, axes = plt.subplots(1, k, figsize=(3.2 * k, 3.4), squeeze=False)
    for i, (ax, a, ends) in enumerate(zip(axes[0], actions_list, ends_list)):
        im = ax.imshow(cosine_similarity_map(a), cmap="viridis", vmin=-1, vmax=1, interpolation="nearest")
        for c in np.asarray(ends)[:-1]:
            ax.axhline(c + 0.5, color="white", lw=1.0)
            ax.axvline(c + 0.5, color="white", lw=1.0)
        if key_steps_list is not None:
            # key step k = first state of a new region = boundary after action k - 1
            ks = np.asarray(key_steps_list[i]) - 0.5
            ax.plot(ks, np.full(len(ks), -0.5), "v", color="red", ms=5, clip_on=False)
            ax.plot(np.full(len(ks), -0.5), ks, ">", color="red", ms=5, clip_on=False)
        ax.set_title(titles[i], fontsize=8)
        ax.set_xlabel("action index", fontsize=7)
        ax.tick_params(labelsize=6)
    fig.colorbar(im, ax=axes[0].tolist(), shrink=0.8, label="cosine similarity")
    note = "white lines: discovered boundaries" + ("; red marks: privileged key steps" if key_steps_list else "")
    fig.suptitle(f"Pairwise action cosine similarity ({note})", fontsize=9)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return out


def plot_sweep(out: Path, tables: dict[str, list[dict]], tol: int) -> Path:
    """Precision / recall against key steps and subskills per demo as functions of beta, one column per cost."""
    fig, axes = plt.subplots(1, len(tables), figsize=(4.6 * len(tables), 3.4), squeeze=False)
    for ax, (cost, rows) in zip(axes[0], tables.items()):
        betas = [r["beta"] for r in rows]
        if "precision" in rows[0]:
            ax.plot(betas, [r["precision"] for r in rows], "o-", label="precision")
            ax.plot(betas, [r["recall"] for r in rows], "s-", label="recall")
            ax.plot(betas, [r["f1"] for r in rows], "^-", label="F1")
        ax.set_xscale("log")
        ax.set_ylim(0, 1.02)
        ax.set_xlabel("beta")
        ax.set_title(f"{cost} (within +-{tol} steps)", fontsize=9)
        ax2 = ax.twinx()
        ax2.plot(betas, [r["subskills_mean"] for r in rows], "k--", lw=1, label="subskills / demo")
        ax2.set_ylabel("subskills / demo (dashed)")
        ax.legend(loc="center left", fontsize=7)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out
