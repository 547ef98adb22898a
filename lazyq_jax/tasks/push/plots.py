"""The push task's figures: Figs. 3-5 of the paper and an animation of evaluation rollouts."""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import jax.numpy as jnp
import numpy as np

from lazyq_jax.config import Config
from lazyq_jax.plots import COLORS, pi_fraction, plt, write_gif
from lazyq_jax.tasks.base import CORRECT, WRONG


def fig3_value(value_fn: Callable, config: Config, path: Path, goals=(np.pi / 2, 5 * np.pi / 4)):
    """Fig. 3: V(s, g) over the finger position s for two goals, with the disk drawn."""
    lim = config.collect.start_range
    xs = np.linspace(-lim, lim, 161, dtype=np.float32)
    grid = np.stack(np.meshgrid(xs, xs), -1).reshape(-1, 2)
    fig, axes = plt.subplots(1, len(goals), figsize=(5.2 * len(goals), 4.6), constrained_layout=True)
    inside = np.linalg.norm(grid, axis=1) <= config.collect.push.contact_distance
    values = [np.where(inside, np.nan, np.asarray(value_fn(jnp.asarray(grid),
                                                            jnp.full(len(grid), g, jnp.float32))))
              for g in goals]  # the finger cannot be inside the disk: left blank
    vmin, vmax = min(np.nanmin(v) for v in values), max(np.nanmax(v) for v in values)
    for ax, g, v, letter in zip(np.atleast_1d(axes), goals, values, "abcd"):
        im = ax.pcolormesh(xs, xs, v.reshape(len(xs), len(xs)), cmap="viridis", vmin=vmin,
                           vmax=vmax, shading="auto")
        ax.add_patch(plt.Circle((0, 0), config.collect.push.disk_radius, fill=False, color="w", lw=1.5))
        ax.annotate("", xy=(0.65 * np.cos(g), 0.65 * np.sin(g)), xytext=(0.33 * np.cos(g), 0.33 * np.sin(g)),
                    arrowprops={"arrowstyle": "-|>", "color": "w", "lw": 2.5})
        ax.text(0, 0, "disk", ha="center", va="center", color="0.3")
        ax.set_title(f"({letter}) V(s, g = {pi_fraction(g)})")
        ax.set_xlabel("finger x (relative to disk)")
        ax.set_ylabel("finger y")
        ax.set_aspect("equal")
    fig.colorbar(im, ax=axes, shrink=0.85, label="V")
    fig.savefig(path, dpi=110)
    plt.close(fig)


def fig4_outcomes(results: dict, path: Path):
    """Fig. 4: one outcome histogram per goal direction, placed around a circle at its angle."""
    per_goal = results["protocol_a"]["per_goal"]
    fig = plt.figure(figsize=(9, 9))
    keys = ("correct", "wrong", "not_pushed")
    for row in per_goal:
        g = row["goal"]
        cx, cy = 0.5 + 0.39 * np.cos(g), 0.5 + 0.39 * np.sin(g)
        ax = fig.add_axes((cx - 0.05, cy - 0.04, 0.1, 0.08))
        total = max(sum(row[k] for k in keys), 1)
        ax.bar(range(3), [row[k] / total for k in keys], color=[COLORS[k] for k in keys])
        ax.set_ylim(0, 1)
        ax.set_xticks([])
        ax.set_yticks([0, 1])
        ax.tick_params(labelsize=7)
        ax.set_title(f"{np.degrees(g):.1f}°", fontsize=8, pad=2)
    center = fig.add_axes((0.3, 0.3, 0.4, 0.4))
    center.add_patch(plt.Circle((0, 0), 0.25, color="0.8"))
    for row in per_goal:
        g = row["goal"]
        center.annotate("", xy=(0.45 * np.cos(g), 0.45 * np.sin(g)), xytext=(0.27 * np.cos(g),
                        0.27 * np.sin(g)), arrowprops={"arrowstyle": "->", "color": "0.4"})
    a = results["protocol_a"]
    center.text(0, -0.62, f"correct: axis {a['axis_correct_rate']:.0%}, all {a['overall_correct_rate']:.0%}",
                ha="center", fontsize=10)
    center.set_xlim(-0.7, 0.7)
    center.set_ylim(-0.7, 0.7)
    center.set_aspect("equal")
    center.axis("off")
    handles = [plt.Rectangle((0, 0), 1, 1, color=COLORS[k]) for k in keys]
    fig.legend(handles, ["correct", "wrong direction", "not pushed"], loc="lower center", ncol=3)
    fig.suptitle("Outcome frequencies per goal direction (protocol A)")
    fig.savefig(path, dpi=110)
    plt.close(fig)


def fig5_trajectories(rollouts, targets, results: dict, table_half_size: float, success_radius: float,
                      path: Path, n: int = 10):
    """Fig. 5: disk trajectories of the first ``n`` long-horizon rollouts."""
    half = table_half_size
    disk = np.asarray(rollouts.obj)  # [T + 1, B, 2]
    steps = np.asarray(rollouts.steps)
    success = np.asarray(rollouts.outcome) == 1
    fig, ax = plt.subplots(figsize=(6.5, 6.5), constrained_layout=True)
    ax.add_patch(plt.Rectangle((-half, -half), 2 * half, 2 * half, color="0.88"))
    for i in range(min(n, disk.shape[1])):
        path_i = disk[: steps[i] + 1, i]
        color = COLORS["correct"] if success[i] else COLORS["wrong"]
        ax.plot(path_i[:, 0], path_i[:, 1], color=color, lw=1.6)
        ax.plot(*path_i[0], marker="D", color=color, ms=6)
        ax.add_patch(plt.Circle(np.asarray(targets)[i], success_radius, fill=False,
                                color=color, lw=1.5))
    b = results["protocol_b"]
    ax.set_title(f"Long-horizon pushes: {b['successes']}/{b['rollouts']} succeeded "
                 f"(first {min(n, disk.shape[1])} shown)")
    ax.set_xlim(-half - 0.05, half + 0.05)
    ax.set_ylim(-half - 0.05, half + 0.05)
    ax.set_aspect("equal")
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _outcome_name(outcome: int) -> str:
    return "correct" if outcome == CORRECT else "wrong" if outcome == WRONG else "not_pushed"


def animate(path: Path, rollouts: dict, config: Config, n_a: int = 2, n_b: int = 2) -> Path:
    """GIF of ``n_a`` protocol-A episodes (an axis and a diagonal goal) and ``n_b``
    long-horizon rollouts: the finger, the disk, the goal (an arrow or the target)."""
    a = rollouts["protocol_a"]
    per = config.eval.episodes_per_direction
    n_dir = config.eval.n_directions
    picks_a = [0] + ([(n_dir // 8) * per] if n_dir >= 8 else [per] if n_dir > 1 else [])
    panels, titles, lengths = [], [], []
    r, half = config.collect.push.disk_radius, config.collect.push.table_half_size
    fr = config.collect.push.finger_radius

    def scene(ax, finger, disk, colour):
        ax.add_patch(plt.Rectangle((-half, -half), 2 * half, 2 * half, color="0.92"))
        ax.add_patch(plt.Circle(tuple(disk), r, color="0.55"))
        ax.add_patch(plt.Circle(tuple(finger), fr, color=colour))

    for b in picks_a[:n_a]:
        g = (b // per) * 2 * np.pi / n_dir
        t_end = int(a.steps[b])
        colour = COLORS[_outcome_name(int(a.outcome[b]))]

        def panel(ax, t, b=b, g=g, t_end=t_end, colour=colour):
            t = min(t, t_end)
            scene(ax, a.agent[t, b], a.obj[t, b], colour if t == t_end else "C0")
            ax.arrow(0, 0, 0.45 * np.cos(g), 0.45 * np.sin(g), width=0.015, color="k", alpha=0.5)
            ax.plot(a.agent[: t + 1, b, 0], a.agent[: t + 1, b, 1], "-", color="C0", lw=1)
            ax.set_xlim(-1.1, 1.1)
            ax.set_ylim(-1.1, 1.1)

        panels.append(panel)
        titles.append(f"goal {np.degrees(g):.0f}°: {_outcome_name(int(a.outcome[b])).replace('_', ' ')}")
        lengths.append(t_end)
    if "protocol_b" in rollouts:
        rb = rollouts["protocol_b"]
        targets = rb.ctx
        for b in range(min(n_b, rb.outcome.shape[0])):
            t_end = int(rb.steps[b])
            colour = COLORS["correct" if int(rb.outcome[b]) == CORRECT else "wrong"]

            def panel(ax, t, b=b, t_end=t_end, colour=colour):
                t = min(t, t_end)
                scene(ax, rb.agent[t, b], rb.obj[t, b], colour if t == t_end else "C0")
                ax.add_patch(plt.Circle(tuple(targets[b]), config.eval.success_radius, fill=False,
                                        color="k", lw=1.5))
                ax.plot(rb.obj[: t + 1, b, 0], rb.obj[: t + 1, b, 1], "-", color="0.3", lw=1)
                ax.set_xlim(-half - 0.1, half + 0.1)
                ax.set_ylim(-half - 0.1, half + 0.1)

            panels.append(panel)
            titles.append("long horizon: " + ("reached" if int(rb.outcome[b]) == CORRECT else "not reached"))
            lengths.append(t_end)
    return write_gif(path, panels, titles, max(lengths), suptitle="push")
