"""Figures of the pointmaze: the maze with each evaluation task's rollouts, and V(s, g) over the
maze for the tasks' goals."""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import jax.numpy as jnp
import numpy as np

from lazyq_jax.plots import plt
from lazyq_jax.tasks.base import CORRECT
from lazyq_jax.tasks.pointmaze.maze import GOAL_TOL, MAZE_UNIT, Maze


def draw_maze(ax, maze: Maze) -> None:
    """The walls as grey squares; axes in the maze's x, y."""
    h = MAZE_UNIT / 2
    for i, j in zip(*np.nonzero(maze.map)):
        x, y = maze.ij_to_xy((i, j))
        ax.add_patch(plt.Rectangle((x - h, y - h), MAZE_UNIT, MAZE_UNIT, color="0.55", lw=0))
    x0, y0, x1, y1 = maze.bounds
    ax.set_xlim(x0 - h, x1 + h)
    ax.set_ylim(y0 - h, y1 + h)
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])


def rollouts_figure(maze: Maze, rollouts, result: dict, path: Path, per_task: int = 5) -> Path:
    """One panel per evaluation task: ``per_task`` of one seed's rollouts (green: reached the
    goal, red: not), starts as dots, goals as circles of the success radius."""
    agent = np.asarray(rollouts.agent)  # [T + 1, B, 2]
    outcome, steps = np.asarray(rollouts.outcome), np.asarray(rollouts.steps)
    goal, task = np.asarray(rollouts.ctx["goal"]), np.asarray(rollouts.ctx["task"])
    tasks = result["tasks"]["per_task"]
    fig, axes = plt.subplots(1, len(tasks), figsize=(3.2 * len(tasks), 3.4), squeeze=False)
    for ax, row in zip(axes[0], tasks):
        draw_maze(ax, maze)
        for b in np.nonzero(task == row["task"])[0][:per_task]:
            ok = outcome[b] == CORRECT
            xy = agent[: steps[b] + 1, b]
            ax.plot(xy[:, 0], xy[:, 1], color="tab:green" if ok else "tab:red", lw=0.8, alpha=0.8)
            ax.plot(*xy[0], "k.", ms=4)
            ax.add_patch(plt.Circle(goal[b], GOAL_TOL, fill=False, color="tab:blue", lw=0.8))
        ax.set_title(f"task {row['task']}: {row['success_rate']:.0%}", fontsize=9)
    fig.suptitle(f"{maze.name} maze, seed {result['seed']}: success "
                 f"{result['tasks']['success_rate']:.1%} "
                 "(mean over tasks)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def value_figure(maze: Maze, value_fn: Callable, path: Path, n: int = 120) -> Path:
    """``V(s, g)`` on a grid of free positions for the goal of each evaluation task."""
    x0, y0, x1, y1 = maze.bounds
    xs, ys = np.linspace(x0, x1, n), np.linspace(y0, y1, n)
    grid = np.stack(np.meshgrid(xs, ys), -1).reshape(-1, 2)
    cells = maze.xy_to_ij(grid)
    free = maze.map[cells[:, 0], cells[:, 1]] == 0
    fig, axes = plt.subplots(1, len(maze.tasks), figsize=(3.2 * len(maze.tasks), 3.4), squeeze=False)
    for ax, (k, (_, goal_ij)) in zip(axes[0], enumerate(maze.tasks)):
        goal = maze.ij_to_xy(goal_ij)
        v = np.asarray(value_fn(jnp.asarray(grid, jnp.float32),
                                jnp.asarray(np.broadcast_to(goal, grid.shape), jnp.float32)))
        img = np.where(free, v, np.nan).reshape(n, n)
        im = ax.imshow(img, origin="lower", extent=(x0, x1, y0, y1), cmap="viridis")
        draw_maze(ax, maze)
        ax.plot(*goal, "r*", ms=10)
        ax.set_title(f"V(s, g) for task {k + 1}'s goal", fontsize=9)
        fig.colorbar(im, ax=ax, fraction=0.046)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
