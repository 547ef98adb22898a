"""Figures 3-5 of the paper from a trained run (matplotlib, PNG)."""

from __future__ import annotations

from fractions import Fraction
from pathlib import Path
from typing import Callable

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import jax.numpy as jnp  # noqa: E402

from lazyq_jax.config import Config  # noqa: E402

COLORS = {"correct": "#2e7d32", "wrong": "#c62828", "not_pushed": "#9e9e9e"}


def _pi_fraction(angle: float) -> str:
    f = Fraction(angle / np.pi).limit_denominator(16)
    num = "" if f.numerator == 1 else str(f.numerator)
    return f"{num}π" if f.denominator == 1 else f"{num}π/{f.denominator}"


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
        ax.set_title(f"({letter}) V(s, g = {_pi_fraction(g)})")
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


def fig5_trajectories(rollouts, targets, results: dict, config: Config, success_radius: float,
                      path: Path, n: int = 10):
    """Fig. 5: disk trajectories of the first ``n`` long-horizon rollouts."""
    half = config.collect.push.table_half_size
    disk = np.asarray(rollouts.disk)  # [T + 1, B, 2]
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


def write_all(out_dir: Path, value_fn, results, rollouts_b, targets, config: Config,
              eval_config) -> list[Path]:
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = [out_dir / "fig3_value.png", out_dir / "fig4_outcomes.png", out_dir / "fig5_long_horizon.png"]
    fig3_value(value_fn, config, paths[0])
    fig4_outcomes(results, paths[1])
    fig5_trajectories(rollouts_b, targets, results, config, eval_config.success_radius, paths[2])
    return paths


def study_per_direction(results: dict, path: Path) -> Path:
    """Correct rate per goal direction (protocol A), mean over seeds with 95 % CI bars,
    one group of bars per direction and one colour per method."""
    path.parent.mkdir(parents=True, exist_ok=True)
    methods = results["methods"]
    fig, ax = plt.subplots(figsize=(11, 4.2), constrained_layout=True)
    width = 0.8 / max(len(methods), 1)
    for j, (name, m) in enumerate(methods.items()):
        rows = m["per_direction"]
        x = np.arange(len(rows)) + (j - (len(methods) - 1) / 2) * width
        mean = np.array([r["mean"] for r in rows])
        low = np.array([r["ci95"][0] if r["ci95"] else r["mean"] for r in rows])
        high = np.array([r["ci95"][1] if r["ci95"] else r["mean"] for r in rows])
        ax.bar(x, mean, width, label=name, yerr=[mean - low, high - mean], capsize=2)
    goals = [r["goal"] for r in next(iter(methods.values()))["per_direction"]]
    ax.set_xticks(np.arange(len(goals)), [f"{np.degrees(g):.1f}°" for g in goals], rotation=45)
    ax.set_ylim(0, 1.05)
    ax.set_ylabel("correct (protocol A)")
    ax.set_xlabel("goal direction (axes at 0°, 90°, 180°, 270°)")
    ax.set_title(f"Correct pushes per goal direction: mean over {len(results['seeds'])} seeds, "
                 "95 % CI")
    if len(methods) > 1:
        ax.legend(ncol=min(len(methods), 8), fontsize=8)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def study_methods(results: dict, path: Path) -> Path:
    """Bar chart of the methods of a study: axis correct, all 16 correct and long-horizon
    success, mean over seeds with 95 % CI bars."""
    path.parent.mkdir(parents=True, exist_ok=True)
    names = list(results["methods"])
    keys = (("axis_correct_rate", "axis goals correct (A)"),
            ("overall_correct_rate", "all 16 goals correct (A)"),
            ("long_horizon_success_rate", "long horizon success (B)"))
    fig, ax = plt.subplots(figsize=(max(7, 1.3 * len(names) + 3), 4.2), constrained_layout=True)
    width = 0.8 / len(keys)
    for j, (key, label) in enumerate(keys):
        rows = [results["methods"][n]["summary"].get(key) for n in names]
        mean = np.array([r["mean"] if r else np.nan for r in rows])
        low = np.array([r["ci95"][0] if r and r["ci95"] else m for r, m in zip(rows, mean)])
        high = np.array([r["ci95"][1] if r and r["ci95"] else m for r, m in zip(rows, mean)])
        x = np.arange(len(names)) + (j - 1) * width
        ax.bar(x, mean, width, label=label, yerr=[mean - low, high - mean], capsize=2)
    ax.set_xticks(np.arange(len(names)), names, rotation=20, ha="right")
    ax.set_ylim(0, 1.05)
    ax.set_ylabel("rate")
    ax.set_title(f"Methods on the same data: mean over {len(results['seeds'])} seeds, 95 % CI")
    ax.legend(fontsize=8, ncol=3, loc="upper center", bbox_to_anchor=(0.5, -0.18))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def online_curve(runs: list[list[dict]], path: Path, static: dict | None = None) -> Path:
    """Online lazy Q's learning curve: protocol A correct rates (all 16 goals, diagonal
    goals) against the simulated moves in the dataset, one record per round
    (:func:`lazyq_jax.online.read_rounds`).  Several runs (seeds) with the same rounds:
    the mean and a 95 % Student-t band.  ``static``: ``{"moves": [...], "all": [(mean, lo,
    hi), ...], "diagonal": [...]}``, the static random dataset of those sizes, drawn as
    points with CI bars."""
    from lazyq_jax.stats import t_interval

    path.parent.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(7, 4.2), constrained_layout=True)
    n_rounds = min(len(r) for r in runs)
    moves = np.mean([[rec["moves_total"] for rec in r[:n_rounds]] for r in runs], axis=0)
    for key, label, colour in (("overall_correct_rate", "all 16 goals", "C0"),
                               ("diagonal_correct_rate", "diagonal goals", "C3")):
        rates = np.array([[rec["protocol_a"][key] for rec in r[:n_rounds]] for r in runs])
        if not np.all(np.isfinite(rates)):  # e.g. no diagonal goals among the directions
            continue
        stats = [t_interval(rates[:, i]) for i in range(n_rounds)]
        ax.plot(moves, [st["mean"] for st in stats], "o-", color=colour, label=f"online, {label}")
        if len(runs) > 1:
            ax.fill_between(moves, [st["ci95"][0] for st in stats], [st["ci95"][1] for st in stats],
                            color=colour, alpha=0.2)
        if static:
            pts = static["all" if key == "overall_correct_rate" else "diagonal"]
            m = np.array([p[0] for p in pts])
            ax.errorbar(static["moves"], m, yerr=[m - [p[1] for p in pts], [p[2] for p in pts] - m],
                        fmt="s--", color=colour, alpha=0.7, capsize=3, label=f"static random, {label}")
    ax.set_xlabel("simulated moves in the dataset")
    ax.set_ylabel("correct (protocol A, per-round episodes)")
    ax.set_ylim(0, 1.05)
    seeds = f"mean over {len(runs)} seeds, 95 % CI" if len(runs) > 1 else "one seed"
    ax.set_title(f"Online lazy Q: correct pushes against data collected ({seeds})")
    ax.legend(fontsize=8)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def arm_value(value_fn: Callable, arm, path: Path, goals=(np.pi / 2, 5 * np.pi / 4), n: int = 40000,
              seed: int = 0, state_of: Callable = lambda q: q) -> Path:
    """The arm's V(q, g) over its fingertip workspace: random joint angles, each drawn at
    its fingertip (inside the table, outside the disk), coloured by V; one panel per goal.
    ``state_of(q)``: the agent's state of joint angles ``q [n, 3]`` (the disk at the origin)."""
    from lazyq_jax.env.arm import fingertip_xy

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
        ax.set_title(f"V(q, g = {_pi_fraction(g)}) at the fingertip of q (max over q: {v.max():.2f})")
        ax.set_aspect("equal")
        ax.set_xlim(-1, 1)
        ax.set_ylim(-1, 1)
    fig.colorbar(sc, ax=axes, shrink=0.8)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def arm_trajectories(rollouts, q, arm, eval_cfg, path: Path, per_direction: int = 1) -> Path:
    """Protocol A with the arm drawn: for the 4 axis and 4 diagonal goals, the first
    ``per_direction`` episodes: the arm at its start (grey) and at its last step
    (coloured by outcome), the fingertip's path and the disk's final position."""
    from lazyq_jax.evaluate import CORRECT, WRONG

    q, fingers, disks = np.asarray(q), np.asarray(rollouts.finger), np.asarray(rollouts.disk)
    outcome, steps = np.asarray(rollouts.outcome), np.asarray(rollouts.steps)
    n_dir, per = eval_cfg.n_directions, eval_cfg.episodes_per_direction
    picks = [d * per + e for d in range(0, n_dir, max(n_dir // 8, 1)) for e in range(min(per_direction, per))]
    cols = 4
    rows = -(-len(picks) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4 * cols, 4 * rows), constrained_layout=True)
    base = np.asarray(arm.base_xy)
    lengths = np.asarray(arm.link_lengths)

    def joints(qq):  # base, elbow, wrist, fingertip
        th = np.cumsum(qq)
        links = lengths[:, None] * np.stack([np.cos(th), np.sin(th)], 1)
        return np.vstack([base, base + np.cumsum(links, 0)])

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
