"""What each exploration choice of online lazy Q does to the data it gathers.

From one trained round-0 agent (an online run's checkpoint at the end of round 0 and
its random dataset), collect one online round with each exploration setting
(``online.epsilon``, ``online.angle_noise``, ``online.start``) and count what the
new moves hold: pushes per 1,000 moves, +1 rewards for axis and for diagonal goal
octants per 1,000 moves (what the diagonal goals lack), and the episodes pushed toward
their own goal.  No training: the settings are compared on the same agent and data.

    .venv/bin/python experiments/online_exploration.py [--run runs/online_s0] [--keys 2]

``--run``: a run of ``python -m lazyq_jax train --preset online`` (any that has its
round-0 checkpoint).  Prints a Markdown table (mean over ``--keys`` collection keys).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np

from lazyq_jax.checkpoint import load_checkpoint
from lazyq_jax.config import from_dict, Config
from lazyq_jax.data import dataset_summary, load_dataset
from lazyq_jax.online import capacity_rows, collect_round, online_functions
from lazyq_jax.types import pad_transitions

SETTINGS = [  # (epsilon, angle_noise, start)
    (0.0, 0.0, "behind"), (0.1, 0.05, "behind"), (0.3, 0.05, "behind"), (0.1, 0.2, "behind"),
    (0.1, 0.5, "behind"), (1.0, 0.0, "behind"), (0.1, 0.05, "anywhere"),
]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--run", type=Path, default=Path("runs/online_s0"))
    ap.add_argument("--keys", type=int, default=2, help="collection rounds (keys) per setting")
    args = ap.parse_args()
    config = from_dict(Config, json.loads((args.run / "config.json").read_text()))
    state, _ = load_checkpoint(args.run / "checkpoints", cycle=config.train.cycles)
    data, _, _ = load_dataset(args.run / "dataset.npz")
    n_goals = config.collect.n_goals
    print("| epsilon | angle noise (rad) | start | pushes / 1k moves | axis +1 / 1k moves | "
          "diagonal +1 / 1k moves | episodes pushed | pushed toward own goal (diagonal goals) |")
    print("|---|---|---|---|---|---|---|---|")
    for eps, noise, start in SETTINGS:
        cfg = dataclasses.replace(config, online=dataclasses.replace(
            config.online, epsilon=eps, angle_noise=noise, start=start))
        fns = online_functions(cfg)
        padded = pad_transitions(data, capacity_rows(cfg))
        rows = []
        for r in range(1, args.keys + 1):
            new, counts = collect_round(cfg, fns, state, padded, data.size, r, quota=10**9)
            octants = dataset_summary(new, n_goals)["reward_by_goal_octant"]
            moves = new.size // n_goals
            rows.append({"pushes": 1000 * int(np.asarray(new.done).sum()) // n_goals / moves,
                         "axis": 1000 * sum(o["positive"] for o in octants[0::2]) / moves,
                         "diag": 1000 * sum(o["positive"] for o in octants[1::2]) / moves,
                         "pushed": counts["pushed"] / counts["episodes"],
                         "own": counts["correct"] / max(counts["pushed"], 1),
                         "own_diag": counts["diagonal_correct"] / counts["diagonal_episodes"]})
        m = {k: np.mean([row[k] for row in rows]) for k in rows[0]}
        print(f"| {eps} | {noise} | {start} | {m['pushes']:.0f} | {m['axis']:.0f} | {m['diag']:.0f} | "
              f"{m['pushed']:.0%} | {m['own']:.0%} ({m['own_diag']:.1%}) |", flush=True)


if __name__ == "__main__":
    main()
