"""The arm's figures: V over the fingertip workspace, protocol A with the arm drawn, and an
animation of evaluation rollouts with the links."""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import jax.numpy as jnp
import numpy as np

from lazyq_jax.plots import COLORS, pi_fraction, plt, write_gif
from lazyq_jax.tasks.arm.env import fingertip_xy
from lazyq_jax.tasks.base import CORRECT, WRONG


def arm_joints(q: np.ndarray, arm) -> np.ndarray:
    """``[4, 2]``: the base, elbow, wrist and fingertip of joint angles ``q [3]``."""
    base, lengths = np.asarray(arm.base_xy), np.asarray(arm.link_lengths)
    th = np.cumsum(q)
    links = lengths[:, None] * np.stack([np.cos(th), np.sin(th)], 1)
    return np.vstack([base, base + np.cumsum(links, 0)])


def arm_value(value_fn: Callable, arm, path: Path, goals=(np.pi / 2, 5 * np.pi / 4), n: int = 40000,
              seed: int = 0, state_of: Callable = lambda q: q) -> Path:
    """The arm's V(q, g) over its fingertip workspace: random joint angles, each drawn at
    its fingertip (inside the table, outside the disk), coloured by V; one panel per goal.
    ``state_of(q)``: the agent's state of joint angles ``q [n, 3]`` (the disk at the origin)."""
    rng = np.random.default_rng(seed)
    q = rng.uniform(arm.joint_lower, arm.joint_upper, (n, 3)).astype(np.float32)
    tip = fingertip_xy(q, arm)
    keep = (np.abs(tip).max(1) <= 1.0) & (np.linalg.norm(tip, axis=1) > arm.contact_distance)
    q, tip = q[keep], tip[keep]
    fig, axes = plt.subplots(1, len(goals), figsize=(5.5 * len(goals), 5), constrained_layout=True)
    s = state_of(jnp.asarray(q))
    values = [np.asarray(value_fn(s, jnp.full(q.shape[0], g, jnp.float32))) for g in goals]
    lo, hi = min(v.min() for v in values), max(v.max() for v in values)  # one scale for all panels
    for ax, g, v in zip(np.atleast_1d(axes), goals, values):
        order = np.argsort(v)  # high values on top
        sc = ax.scatter(tip[order, 0], tip[order, 1], c=v[order], s=2, cmap="viridis", vmin=lo, vmax=hi)
        ax.add_patch(plt.Circle((0, 0), arm.push.disk_radius, fill=False, color="k"))
        ax.arrow(0, 0, 0.4 * np.cos(g), 0.4 * np.sin(g), width=0.02, color="w", ec="k")
        ax.set_title(f"V(q, g = {pi_fraction(g)}) at the fingertip of q (max over q: {v.max():.2f})")
        ax.set_aspect("equal")
        ax.set_xlim(-1, 1)
        ax.set_ylim(-1, 1)
    fig.colorbar(sc, ax=axes, shrink=0.8)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def arm_trajectories(rollouts, arm, eval_cfg, path: Path, per_direction: int = 1) -> Path:
    """Protocol A with the arm drawn: for the 4 axis and 4 diagonal goals, the first
    ``per_direction`` episodes: the arm at its start (grey) and at its last step
    (coloured by outcome), the fingertip's path and the disk's final position."""
    q, fingers, disks = np.asarray(rollouts.extra), np.asarray(rollouts.agent), np.asarray(rollouts.obj)
    outcome, steps = np.asarray(rollouts.outcome), np.asarray(rollouts.steps)
    n_dir, per = eval_cfg.n_directions, eval_cfg.episodes_per_direction
    picks = [d * per + e for d in range(0, n_dir, max(n_dir // 8, 1)) for e in range(min(per_direction, per))]
    cols = 4
    rows = -(-len(picks) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4 * cols, 4 * rows), constrained_layout=True)
    joints = lambda qq: arm_joints(qq, arm)
    for ax, b in zip(np.ravel(axes), picks):
        g = (b // per) * 2 * np.pi / n_dir
        t = int(steps[b])
        key = "correct" if outcome[b] == CORRECT else "wrong" if outcome[b] == WRONG else "not_pushed"
        ax.plot(*joints(q[0, b]).T, "-o", color="0.6", ms=3)
        ax.plot(*joints(q[t, b]).T, "-o", color=COLORS[key], ms=3)
        ax.plot(fingers[: t + 1, b, 0], fingers[: t + 1, b, 1], ".-", color="C0", ms=2, lw=1)
        ax.add_patch(plt.Circle((0, 0), arm.push.disk_radius, fill=False, color="0.6", ls="--"))
        ax.add_patch(plt.Circle(tuple(disks[t, b]), arm.push.disk_radius, fill=False, color="k"))
        ax.arrow(0, 0, 0.35 * np.cos(g), 0.35 * np.sin(g), width=0.015, color=COLORS[key])
        ax.set_title(f"goal {np.degrees(g):.0f}°: {key.replace('_', ' ')} after {t} steps", fontsize=9)
        ax.set_aspect("equal")
        ax.set_xlim(-1.1, 1.1)
        ax.set_ylim(-1.15, 1.1)
    for ax in np.ravel(axes)[len(picks):]:
        ax.axis("off")
    fig.suptitle("Arm, protocol A: start (grey) and end pose, fingertip path (blue), disk (black)")
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def animate(path: Path, rollouts: dict, config, n_a: int = 2, n_b: int = 2) -> Path:
    """GIF of ``n_a`` protocol-A episodes (an axis and a diagonal goal) and, with the disk in
    the state, ``n_b`` long-horizon rollouts: the arm's links, the fingertip, the disk."""
    arm, cfg = config.collect.arm, config.eval
    r, half = arm.push.disk_radius, arm.push.table_half_size
    per, n_dir = cfg.episodes_per_direction, cfg.n_directions
    a = rollouts["protocol_a"]
    picks = [0] + ([(n_dir // 8) * per] if n_dir >= 8 else [per] if n_dir > 1 else [])
    panels, titles, lengths = [], [], []

    def scene(ax, roll, b, t, t_end):
        t = min(t, t_end)
        ax.add_patch(plt.Rectangle((-half, -half), 2 * half, 2 * half, color="0.92"))
        ax.add_patch(plt.Circle(tuple(roll.obj[t, b]), r, color="0.55"))
        name = ("correct" if roll.outcome[b] == CORRECT else "wrong" if roll.outcome[b] == WRONG
                else "not_pushed")
        ax.plot(*arm_joints(roll.extra[t, b], arm).T, "-o", color=COLORS[name] if t == t_end else "C0",
                ms=3, lw=2)
        ax.plot(roll.agent[: t + 1, b, 0], roll.agent[: t + 1, b, 1], "-", color="C0", lw=0.8)
        ax.set_xlim(-1.2, 1.2)
        ax.set_ylim(-1.15, 1.2)

    for b in picks[:n_a]:
        g, t_end = (b // per) * 2 * np.pi / n_dir, int(a.steps[b])

        def panel(ax, t, b=b, g=g, t_end=t_end):
            scene(ax, a, b, t, t_end)
            ax.arrow(0, 0, 0.45 * np.cos(g), 0.45 * np.sin(g), width=0.015, color="k", alpha=0.5)

        panels.append(panel)
        titles.append(f"goal {np.degrees(g):.0f}°")
        lengths.append(t_end)
    if "protocol_b" in rollouts:
        rb = rollouts["protocol_b"]
        targets = rb.ctx
        for b in range(min(n_b, rb.outcome.shape[0])):
            t_end = int(rb.steps[b])

            def panel(ax, t, b=b, t_end=t_end):
                scene(ax, rb, b, t, t_end)
                ax.add_patch(plt.Circle(tuple(targets[b]), cfg.success_radius, fill=False, color="k"))

            panels.append(panel)
            titles.append("long horizon: " + ("reached" if rb.outcome[b] == CORRECT else "not reached"))
            lengths.append(t_end)
    return write_gif(path, panels, titles, max(lengths), suptitle=config.task)
