"""One pointmaze table over seeds that were run in separate run directories (one seed
each, so every method runs unbatched as in ``train``): mean [95 % CI] of the success
rate and of each task per method, and each method's paired difference to the first
one (the seeds share their datasets and evaluation episodes).  Reads
``<run>/results.json`` and ``<run>/<method>/timings.json``; trains nothing.

    .venv/bin/python experiments/pointmaze_table.py runs/pm_goaloff runs/pm_ogb runs/pm_s1 \\
        runs/pm_s2 --methods lazy gcivl:width=128:steps=114139
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from lazyq_jax.stats import format_ci, t_interval

KEYS = ("success_rate", "task1", "task2", "task3", "task4", "task5")


def per_seed_rows(run_dirs: list[Path], method: str) -> dict[int, dict]:
    """``seed -> {result keys, "train_s"}`` of ``method`` over the run directories; a seed
    found twice is an error (which run would count?)."""
    rows: dict[int, dict] = {}
    for run_dir in run_dirs:
        results = json.loads((run_dir / "results.json").read_text())
        if method not in results["methods"]:
            continue
        timings = results["methods"][method].get("timings", {})
        for row in results["methods"][method]["per_seed"]:
            if row["seed"] in rows:
                raise SystemExit(f"{method}: seed {row['seed']} is in two of the run directories "
                                 f"(again in {run_dir}); name each seed's run once")
            spent = timings.get("train_s", float("nan")) + timings.get("prepare_s", 0.0)
            rows[row["seed"]] = {**row, "train_s": spent / len(results["seeds"])}
    return rows


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("run_dirs", nargs="+", type=Path)
    p.add_argument("--methods", nargs="+", required=True,
                   help="method specs as in results.json; the first is the reference of the "
                        "paired differences")
    args = p.parse_args()
    # the seeds' data and evaluation must come from the same settings (a seed's dataset is a
    # function of its seed and the collect settings)
    settings = {str(d): {k: json.loads((d / "run.json").read_text())["config"][k]
                         for k in ("task", "collect", "eval")} for d in args.run_dirs}
    first = next(iter(settings.values()))
    for d, cfg in settings.items():
        if cfg != first:
            raise SystemExit(f"{d} has other task/collect/eval settings than {args.run_dirs[0]}")
    table = {m: per_seed_rows(args.run_dirs, m) for m in args.methods}
    for m, rows in table.items():
        if not rows:
            raise SystemExit(f"{m}: in none of {[str(d) for d in args.run_dirs]}")
    print("| method | seeds | success | task 1 | task 2 | task 3 | task 4 | task 5 | train s / seed |")
    print("|---|---|---|---|---|---|---|---|---|")
    for m, rows in table.items():
        seeds = sorted(rows)
        cells = [format_ci(t_interval([rows[s][k] for s in seeds])) for k in KEYS]
        train = np.mean([rows[s]["train_s"] for s in seeds])
        print(f"| {m} | {','.join(map(str, seeds))} | " + " | ".join(cells) + f" | {train:.0f} |")
    ref_name, ref = args.methods[0], table[args.methods[0]]
    for m in args.methods[1:]:
        common = sorted(set(ref) & set(table[m]))
        if len(common) < 2:
            continue
        diff = [table[m][s]["success_rate"] - ref[s]["success_rate"] for s in common]
        ci = t_interval(diff, bounds=None)
        print(f"{m} - {ref_name} (paired over seeds {common}): "
              f"{format_ci(ci).replace(' %', ' points')}")


if __name__ == "__main__":
    main()
