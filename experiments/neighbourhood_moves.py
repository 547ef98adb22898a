"""How many distinct moves a lazy Q neighbourhood holds: the dataset stores every simulated
move with ``collect.n_goals`` goals (§V-A-3), so ``k`` neighbours can be a few moves copied
with nearby goals, and Eq. (6)'s fit of ``beta`` sees only those few actions.

For each run directory and seed: the neighbourhoods of every row as lazy Q's training draws
them (its ``prepare``: the run's feature map, radii, ``k`` and key), then the number of
distinct moves (rows with the same state and action) and of distinct actions among each
row's ``k`` neighbours.  Prints for both the mean, median, the fractions with one and with at
most two, and with fewer than ``1 + n_a`` (what Eq. (6)'s ``alpha, beta`` need).
Trains nothing; needs only the datasets: a run directory's, or those that ``collect`` wrote
(no ``run.json``: then ``--task``, ``--preset`` and ``--set`` say how they were made).

    .venv/bin/python experiments/neighbourhood_moves.py \\
        runs/arm_levers/arm-long/fingertip_offsets_box0.6_disk0.3_x4_g25_random --seeds 0
    .venv/bin/python -m lazyq_jax collect --task arm-long --run-dir runs/armlong_1x
    .venv/bin/python experiments/neighbourhood_moves.py runs/armlong_1x --task arm-long
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from lazyq_jax import agents, tasks
from lazyq_jax.agents.lazy import LazyConfig
from lazyq_jax.config import override
from lazyq_jax.data import load_dataset
from lazyq_jax.run.rundir import RunDirError
from lazyq_jax.run.runner import open_existing


def row_ids(*columns: np.ndarray) -> np.ndarray:
    """One id per distinct row of the concatenated ``columns``: (state, action) gives the rows
    of one move relabelled with goals; the action alone joins the moves that share it (the
    data's two moves from one start take the same joint direction)."""
    rows = np.ascontiguousarray(np.concatenate(columns, 1).astype(np.float32))
    _, ids = np.unique(rows.view(np.dtype((np.void, rows.dtype.itemsize * rows.shape[1]))),
                       return_inverse=True)
    return ids.reshape(-1)


def distinct_per_row(ids_nb: np.ndarray) -> np.ndarray:
    """Distinct values in each row of ``ids_nb [N, k]``."""
    srt = np.sort(ids_nb, axis=1)
    return 1 + np.count_nonzero(np.diff(srt, axis=1), axis=1)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run_dirs", type=Path, nargs="+")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--task", help="for directories without run.json: the task that collected them")
    ap.add_argument("--preset", default="paper")
    ap.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE")
    args = ap.parse_args()
    out = {}
    for run_dir in args.run_dirs:
        try:
            config, _ = open_existing(run_dir)
        except RunDirError:
            if args.task is None:
                raise SystemExit(f"{run_dir} has no run.json: say with --task (and --set) how its "
                                 "data were collected") from None
            config = override(tasks.preset(args.task, args.preset), args.set)
        problem = tasks.get(config.task).problem(config)
        agent = agents.make("lazy", LazyConfig(train=config.train, neighbours=config.neighbours),
                            problem=problem)
        for seed in args.seeds:
            data, _ = load_dataset(run_dir / "data" / str(seed) / "dataset.npz")
            n = int(data.r.shape[0])
            t = time.perf_counter()
            idx = np.asarray(agent.prepare(seed, data, n, 0).idx)
            s, a = np.asarray(data.s), np.asarray(data.a)
            moves = row_ids(s, a)
            coef = 1 + int(a.shape[-1])
            row = {"rows": n, "moves": int(moves.max()) + 1, "k": int(idx.shape[1])}
            for what, ids in (("moves", moves), ("actions", row_ids(a))):
                counts = distinct_per_row(ids[idx])
                row[what + "_in_neighbourhood"] = stats = {
                    "mean": float(counts.mean()), "median": float(np.median(counts)),
                    "one": float(np.mean(counts == 1)), "at_most_two": float(np.mean(counts <= 2)),
                    f"below_{coef}": float(np.mean(counts < coef))}
                print(f"{run_dir} seed {seed}: {n:,} rows, {row['moves']:,} moves "
                      f"({n / row['moves']:.1f} goals each); k = {row['k']} neighbours hold "
                      f"{stats['mean']:.2f} distinct {what} on average (median {stats['median']:.0f}; "
                      f"one: {stats['one']:.2%}, <= 2: {stats['at_most_two']:.1%}, "
                      f"< {coef}: {stats[f'below_{coef}']:.1%})", flush=True)
            row["seconds"] = time.perf_counter() - t
            out[f"{run_dir}/{seed}"] = row
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
