"""Figures that do not depend on a task: the study's comparisons (rates per method and
per goal direction, mean over seeds with 95 % CI), online learning curves, and the GIF
writer the tasks' animations use (matplotlib only: no OpenGL)."""

from __future__ import annotations

from fractions import Fraction
from pathlib import Path
from typing import Callable, Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.animation import FuncAnimation, PillowWriter  # noqa: E402

from lazyq_jax.stats import t_interval  # noqa: E402

COLORS = {"correct": "#2e7d32", "wrong": "#c62828", "not_pushed": "#9e9e9e"}


def pi_fraction(angle: float) -> str:
    f = Fraction(angle / np.pi).limit_denominator(16)
    num = "" if f.numerator == 1 else str(f.numerator)
    return f"{num}π" if f.denominator == 1 else f"{num}π/{f.denominator}"


def study_per_direction(results: dict, path: Path) -> Path:
    """Correct rate per goal direction (protocol A), mean over seeds with 95 % CI bars,
    one group of bars per direction and one colour per method."""
    path.parent.mkdir(parents=True, exist_ok=True)
    methods = {name: m for name, m in results["methods"].items() if m.get("per_direction")}
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


def study_methods(results: dict, rates: Sequence[tuple[str, str]], path: Path) -> Path:
    """Bar chart of the methods of a study: the task's ``rates`` (key, label), mean over
    seeds with 95 % CI bars."""
    path.parent.mkdir(parents=True, exist_ok=True)
    names = list(results["methods"])
    keys = [(key, label) for key, label in rates
            if any(key in m["summary"] for m in results["methods"].values())]
    fig, ax = plt.subplots(figsize=(max(7, 1.3 * len(names) + 3), 4.2), constrained_layout=True)
    width = 0.8 / len(keys)
    for j, (key, label) in enumerate(keys):
        rows = [results["methods"][n]["summary"].get(key) for n in names]
        mean = np.array([r["mean"] if r else np.nan for r in rows])
        low = np.array([r["ci95"][0] if r and r["ci95"] else m for r, m in zip(rows, mean)])
        high = np.array([r["ci95"][1] if r and r["ci95"] else m for r, m in zip(rows, mean)])
        x = np.arange(len(names)) + (j - (len(keys) - 1) / 2) * width
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
    (``online/rounds.jsonl``).  Several runs (seeds) with the same rounds:
    the mean and a 95 % Student-t band.  ``static``: ``{"moves": [...], "all": [(mean, lo,
    hi), ...], "diagonal": [...]}``, the static random dataset of those sizes, drawn as
    points with CI bars."""
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


def write_gif(path: Path, panels: Sequence[Callable], titles: Sequence[str], last_step: int, *,
              max_frames: int = 30, fps: int = 6, size: float = 3.4, suptitle: str = "") -> Path:
    """An animated GIF of ``len(panels)`` side-by-side panels over the steps ``0 ..
    last_step`` (at most ``max_frames`` frames, evenly spaced): each frame calls
    ``panel(ax, t)`` on a cleared axis for each panel, which draws the scene at step
    ``t`` (a finished episode keeps drawing its last step)."""
    times = np.unique(np.round(np.linspace(0, last_step, min(last_step + 1, max_frames))).astype(int))
    path.parent.mkdir(parents=True, exist_ok=True)
    fig, axes = plt.subplots(1, len(panels), figsize=(size * len(panels), size + 0.4),
                             constrained_layout=True)
    axes = np.atleast_1d(axes)

    def draw(frame):
        t = int(times[frame])
        for ax, panel, title in zip(axes, panels, titles):
            ax.clear()
            panel(ax, t)
            ax.set_title(title, fontsize=8)
            ax.set_aspect("equal")
            ax.set_xticks([])
            ax.set_yticks([])
        fig.suptitle(f"{suptitle}  step {t}".strip(), fontsize=9)
        return []

    FuncAnimation(fig, draw, frames=len(times), blit=False).save(path, writer=PillowWriter(fps=fps), dpi=64)
    plt.close(fig)
    return path
