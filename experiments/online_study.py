"""Online lazy Q against the static random dataset: the learning curve of the README.

Runs (or resumes) two studies on the same seeds and draws one figure:

* ``--online``: ``python -m lazyq_jax study --preset online`` (round 0: 2,500 random
  starts, about 5,000 moves; then 5 rounds of the agent's own pushes; at most 20,000
  simulated moves), per round protocol A on 10 episodes per direction;
* ``--static``: the paper's method on one static random dataset of the same final size
  (10,000 random starts, about 19,900 moves), same training per cycle, 10 cycles;
* ``--paper``: an existing study of the paper's preset (10,000 moves, ``make study``),
  drawn as a third static point if it exists.

    .venv/bin/python experiments/online_study.py [--seeds 3] [--online runs/study_online]
        [--static runs/study_static20k] [--paper runs/study_paper] [--set online.epsilon=0.2]

Writes ``<online>/figures/online_vs_static.png`` and prints the table of the README.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from lazyq_jax import plots
from lazyq_jax.config import override, preset
from lazyq_jax.online import read_rounds
from lazyq_jax.stats import format_ci, t_interval
from lazyq_jax.study import run_study


def static_point(results: dict) -> tuple[float, dict]:
    """(mean moves, {rate: (mean, low, high)}) of a static study's lazy Q."""
    moves = float(np.mean(results["datasets"]["rows"])) / 100  # n_goals = 100 in both presets
    summary = results["methods"]["lazy"]["summary"]
    point = {}
    for key, name in (("overall_correct_rate", "all"), ("diagonal_correct_rate", "diagonal")):
        s = summary[key]
        low, high = s["ci95"] if s["ci95"] else (s["mean"], s["mean"])
        point[name] = (s["mean"], low, high)
    return moves, point


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--online", type=Path, default=Path("runs/study_online"))
    ap.add_argument("--static", type=Path, default=Path("runs/study_static20k"))
    ap.add_argument("--paper", type=Path, default=Path("runs/study_paper"))
    ap.add_argument("--set", action="append", default=[], help="online config override")
    args = ap.parse_args()
    seeds = list(range(args.seeds))
    online = override(preset("online"), args.set)
    on = run_study(online, args.online, seeds=seeds, resume=True, progress=False)
    static_cfg = override(preset("paper"), [f"collect.n_starts={4 * online.collect.n_starts}"])
    st = run_study(static_cfg, args.static, seeds=seeds, resume=True, progress=False)

    statics = [st]
    if (args.paper / "results.json").exists():
        statics.insert(0, json.loads((args.paper / "results.json").read_text()))
    points = sorted(static_point(r) for r in statics)
    static = {"moves": [m for m, _ in points], "all": [p["all"] for _, p in points],
              "diagonal": [p["diagonal"] for _, p in points]}
    runs = [read_rounds(args.online / "seeds" / str(s)) for s in seeds]
    path = plots.online_curve(runs, args.online / "figures" / "online_vs_static.png", static)

    print("| data | moves | axis correct | diagonal correct | all 16 correct | long horizon | seeds |")
    print("|---|---|---|---|---|---|---|")
    rows = [("online (final)", on, float(np.mean([r[-1]["moves_total"] for r in runs])))]
    rows += [("static random", r, m) for r, (m, _) in zip(statics, points)]
    for name, res, moves in rows:
        s = res["methods"]["lazy"]["summary"]
        print(f"| {name} | {moves:,.0f} | {format_ci(s['axis_correct_rate'])} | "
              f"{format_ci(s['diagonal_correct_rate'])} | {format_ci(s['overall_correct_rate'])} | "
              f"{format_ci(s['long_horizon_success_rate'])} | {len(res['seeds'])} |")
    print("\nper round (protocol A, 10 episodes per direction), mean [95 % CI] over seeds:")
    for i in range(min(len(r) for r in runs)):
        moves = np.mean([r[i]["moves_total"] for r in runs])
        pushes = np.mean([r[i]["pushes_added"] for r in runs])
        cells = [format_ci(t_interval([r[i]["protocol_a"][k] for r in runs]))
                 for k in ("axis_correct_rate", "diagonal_correct_rate", "overall_correct_rate")]
        diag_pos = np.mean([sum(o["positive"] for o in r[i]["reward_by_goal_octant"][1::2]) for r in runs])
        print(f"round {i}: {moves:,.0f} moves, +{pushes:.0f} pushes, diagonal positives added "
              f"{diag_pos:.0f}; axis {cells[0]}, diagonal {cells[1]}, all {cells[2]}")
    print(f"figure: {path}")


if __name__ == "__main__":
    main()
