"""Figures of the cube task: each evaluation task's rollouts seen from above (the cube's and the
effector's paths), and the cube's height over time (grasped and lifted, or pushed along the
table)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lazyq_jax.plots import plt
from lazyq_jax.tasks.base import CORRECT
from lazyq_jax.tasks.cube.env import GOAL_TOL

TABLE = ((0.25, 0.6), (-0.35, 0.35))  # OGBench's workspace bounds in x and y (metres)


def rollouts_figure(rollouts, result: dict, path: Path, per_task: int = 5) -> Path:
    """Top row, one panel per task: ``per_task`` of one seed's episodes, the cube's path (green:
    success, red: not; a dot at its start) and the effector's (grey), the target as a circle of
    the success radius.  Bottom row: the cube's height over the steps of the same episodes."""
    eff, cube = np.asarray(rollouts.agent), np.asarray(rollouts.obj)  # [T + 1, B, 3]
    outcome, steps = np.asarray(rollouts.outcome), np.asarray(rollouts.steps)
    target, task = np.asarray(rollouts.ctx["target"]), np.asarray(rollouts.ctx["task"])
    rows = result["tasks"]["per_task"]
    fig, axes = plt.subplots(2, len(rows), figsize=(3.0 * len(rows), 6.0), squeeze=False,
                             gridspec_kw={"height_ratios": [2, 1]})
    for k, row in enumerate(rows):
        top, side = axes[0, k], axes[1, k]
        for b in np.nonzero(task == row["task"])[0][:per_task]:
            colour = "tab:green" if outcome[b] == CORRECT else "tab:red"
            n = steps[b] + 1
            top.plot(eff[:n, b, 1], eff[:n, b, 0], color="0.6", lw=0.6)
            top.plot(cube[:n, b, 1], cube[:n, b, 0], color=colour, lw=1.2)
            top.plot(cube[0, b, 1], cube[0, b, 0], ".", color=colour, ms=5)
            top.add_patch(plt.Circle((target[b, 1], target[b, 0]), GOAL_TOL, fill=False,
                                     color="tab:blue", lw=0.8))
            side.plot(np.arange(n), cube[:n, b, 2], color=colour, lw=0.8)
        top.set_xlim(*TABLE[1])
        top.set_ylim(*TABLE[0])
        top.set_aspect("equal")
        top.set_xlabel("y (m)", fontsize=8)
        top.set_ylabel("x (m)", fontsize=8)
        top.set_title(f"task {row['task']}: {row['success_rate']:.0%}", fontsize=9)
        side.set_xlabel("step", fontsize=8)
        side.set_ylabel("cube height (m)", fontsize=8)
    fig.suptitle(f"cube-single, seed {result['seed']}: success {result['tasks']['success_rate']:.1%} "
                 "(mean over tasks); cube paths green/red, effector grey", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
