"""Figure of Moving Maze configurations with demo paths: ``python -m cotpc.envs.maze.figure OUT.png``.

Each panel is one training configuration: islands (blue), the blocks at their initial positions (green, the
target gold), the band each moving block travels (light green), and the demo path coloured by region with the
privileged key steps (region entries) marked.
"""

from __future__ import annotations

import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.patches import Rectangle  # noqa: E402

from cotpc.data.targets import key_state_indices  # noqa: E402
from cotpc.envs.maze.demos import plan_demo  # noqa: E402

from cotpc.envs.maze.env import (  # noqa: E402
    BLOCK,
    BRIDGE1_X_RANGE,
    BRIDGE1_Y,
    BRIDGE2_X_RANGE,
    BRIDGE2_Y,
    HEIGHT,
    ISLANDS,
    TARGET_Y_RANGE,
    WIDTH,
    block_rects,
    seeds_for,
)


def draw_maze(ax, obs0: np.ndarray) -> None:
    """Draw the maze as it is at the state ``obs0`` (10-dim observation)."""
    h = BLOCK / 2
    for x0, x1, y0, y1 in ISLANDS:
        ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, color="#4a6ec8"))
    bands = [
        (BRIDGE1_X_RANGE[0] - h, BRIDGE1_Y - h, BRIDGE1_X_RANGE[1] - BRIDGE1_X_RANGE[0] + BLOCK, BLOCK),
        (BRIDGE2_X_RANGE[0] - h, BRIDGE2_Y - h, BRIDGE2_X_RANGE[1] - BRIDGE2_X_RANGE[0] + BLOCK, BLOCK),
        (0.0, TARGET_Y_RANGE[0] - h, BLOCK, TARGET_Y_RANGE[1] - TARGET_Y_RANGE[0] + BLOCK),
    ]
    for x, y, w, hh in bands:
        ax.add_patch(Rectangle((x, y), w, hh, color="#3caa5a", alpha=0.15, lw=0))
    rects = block_rects(np.array([obs0[3]], float), np.array([[obs0[4], obs0[6], obs0[9]]], float))[0]
    for i, (x0, x1, y0, y1) in enumerate(rects):
        ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, color="#f0b428" if i == 3 else "#3caa5a", alpha=0.9))
    ax.set_xlim(-2, WIDTH + 2)
    ax.set_ylim(-7, HEIGHT + 7)
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])


def draw_path(ax, obs: np.ndarray, key_steps: np.ndarray | None = None) -> None:
    ax.plot(obs[:, 0], obs[:, 1], "-", color="#801414", lw=1.2)
    ax.plot(obs[:, 0], obs[:, 1], ".", color="#801414", ms=3)
    ax.plot(*obs[0, :2], "o", color="#dc2828", ms=6)
    if key_steps is not None:
        ax.plot(obs[key_steps, 0], obs[key_steps, 1], "*", color="black", ms=9, label="key steps")


def make_figure(out: str, num: int = 6) -> None:
    fig, axes = plt.subplots(1, num, figsize=(2.2 * num, 3.4))
    for ax, seed in zip(axes, seeds_for("train", num)):
        config, obs, actions, key_steps = plan_demo(int(seed))
        draw_maze(ax, obs[0])
        draw_path(ax, obs, key_steps)
        ax.set_title(f"seed {seed}: {len(actions)} steps", fontsize=8)
    axes[0].legend(loc="lower right", fontsize=6)
    fig.suptitle("Moving Maze: initial configurations, travel bands (light) and demo paths", fontsize=9)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


def plot_maze_paths(out: Path, episodes, ends_list, titles) -> Path:
    """Moving Maze demos (obs[:, :2] = agent x, y): the path coloured by subskill, discovered key states
    (``obs[c_i + 1]``) as circles, privileged ``key_steps`` as black crosses."""
    k = len(episodes)
    fig, axes = plt.subplots(1, k, figsize=(2.4 * k, 3.6), squeeze=False)
    cmap = plt.get_cmap("tab10")
    for ax, ep, ends, title in zip(axes[0], episodes, ends_list, titles):
        obs = ep.obs
        draw_maze(ax, obs[0])
        start = 0
        for s, c in enumerate(ends):  # segment s: states start .. c + 1
            xy = obs[start : int(c) + 2, :2]
            ax.plot(xy[:, 0], xy[:, 1], "-", color=cmap(s % 10), lw=1.6)
            ax.plot(xy[:-1, 0], xy[:-1, 1], ".", color=cmap(s % 10), ms=3)
            start = int(c) + 1
        ax.plot(*obs[0, :2], "s", color="black", ms=4)
        key = obs[key_state_indices(ends)[:-1], :2]
        ax.plot(key[:, 0], key[:, 1], "o", mfc="none", mec="red", mew=1.5, ms=8, label="discovered key states")
        if "key_steps" in ep.extras:
            true = obs[np.asarray(ep.extras["key_steps"]), :2]
            ax.plot(true[:, 0], true[:, 1], "x", color="black", mew=1.5, ms=6, label="privileged key steps")
        ax.set_title(title, fontsize=8)
    axes[0][0].legend(loc="lower right", fontsize=6)
    fig.suptitle("Moving Maze demos coloured by discovered subskill", fontsize=9)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return out


if __name__ == "__main__":
    make_figure(sys.argv[1] if len(sys.argv) > 1 else "docs/img/moving-maze.png")
