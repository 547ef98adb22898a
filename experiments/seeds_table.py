"""One table over seeds that were run in separate run directories (resumed studies, seeds
added later, or one seed a directory so that every method runs unbatched as in
``train``): mean [95 % CI] over the seeds of the task's rates per method, and each
method's paired difference to the first one (the seeds share their datasets and
evaluation episodes).  Lazy Q's rows name the policy settings they were evaluated with
(the runs' own or ``evaluate --set``'s) and must agree on them.  Reads ``<run>/run.json`` and ``<run>/results.json``; trains
nothing.  The runs must agree on every setting but the seed (``--same`` narrows the check
to some sections, e.g. when each method was trained in its own run directory).

    .venv/bin/python experiments/seeds_table.py runs/arm_levers/arm/online_fingertip_offsets_x4 \\
        runs/arm_levers_s34/arm/online_fingertip_offsets_x4 --methods lazy
    .venv/bin/python experiments/seeds_table.py runs/pm_goaloff runs/pm_ogb runs/pm_s1 runs/pm_s2 \\
        --methods lazy gcivl:width=128:steps=114139 --same task collect eval
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np

from lazyq_jax import tasks
from lazyq_jax.config import policy_settings
from lazyq_jax.run.rundir import as_json
from lazyq_jax.run.runner import open_existing
from lazyq_jax.stats import format_ci, t_interval

NOT_COMPARED = ("seed", "parallel")  # what may differ between the runs of one table


def policy(run_dir: Path, method: dict) -> dict:
    """Lazy Q's policy settings (``POLICY_FIELDS``) that produced a run's results: the run's
    own, changed where ``evaluate --set`` changed them (the results' ``"acting"``)."""
    return {**policy_settings(open_existing(run_dir)[0]), **method.get("acting", {})}


def per_seed_rows(run_dirs: list[Path], method: str) -> dict[int, dict]:
    """``seed -> {result keys, "train_s"}`` of ``method`` over the run directories (lazy Q's
    rows also ``"policy"``, the settings they were evaluated with: :func:`policy`); a seed
    found twice is an error (which run would count?), and so are lazy Q's results of other
    policy settings (e.g. one run evaluated with the two-level step, another without)."""
    rows: dict[int, dict] = {}
    acting: dict[str, dict] = {}
    for run_dir in run_dirs:
        results = json.loads((run_dir / "results.json").read_text())
        if method not in results["methods"]:
            continue
        settings = {}
        if method.split(":")[0] == "lazy":
            settings = {"policy": policy(run_dir, results["methods"][method])}
            acting[str(run_dir)] = settings["policy"]
            if len({json.dumps(a, sort_keys=True) for a in acting.values()}) > 1:
                raise SystemExit(f"{method}: the runs were evaluated with other policy settings: "
                                 f"{acting}; evaluate them alike (evaluate --set)")
        timings = results["methods"][method].get("timings", {})
        for row in results["methods"][method]["per_seed"]:
            if row["seed"] in rows:
                raise SystemExit(f"{method}: seed {row['seed']} is in two of the run directories "
                                 f"(again in {run_dir}); name each seed's run once")
            spent = timings.get("train_s", float("nan")) + timings.get("prepare_s", 0.0)
            rows[row["seed"]] = {**row, "train_s": spent / len(results["seeds"]), **settings}
    return rows


def check_settings(run_dirs: list[Path], same: list[str] | None) -> str:
    """The runs' common task; exits naming the first section that differs.  Each stored
    config is read back as the runner reads it (a field added to lazyq-jax later takes its
    default, as it did when the run was made)."""
    configs = {str(d): as_json(dataclasses.asdict(open_existing(d)[0])) for d in run_dirs}
    first_dir, first = next(iter(configs.items()))
    sections = same or [k for k in first if k not in NOT_COMPARED]
    for d, cfg in configs.items():
        for key in sections:
            if cfg.get(key) != first.get(key):
                raise SystemExit(f"{d} has other {key!r} settings than {first_dir}; a table over seeds "
                                 "needs the same settings (--same narrows the check)")
    return first["task"]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("run_dirs", nargs="+", type=Path)
    p.add_argument("--methods", nargs="+", required=True,
                   help="method specs as in results.json; the first is the reference of the "
                        "paired differences")
    p.add_argument("--same", nargs="+", default=None,
                   help="config sections that must agree (default: all but seed and parallel)")
    args = p.parse_args()
    task = tasks.get(check_settings(args.run_dirs, args.same))
    table = {m: per_seed_rows(args.run_dirs, m) for m in args.methods}
    for m, rows in table.items():
        if not rows:
            raise SystemExit(f"{m}: in none of {[str(d) for d in args.run_dirs]}")
    print("| method | seeds | " + " | ".join(label for _, label in task.rates) + " | s / seed |")
    print("|---|---|" + "---|" * len(task.rates) + "---|")
    for m, rows in table.items():
        seeds = sorted(rows)
        cells = [format_ci(t_interval([rows[s][k] for s in seeds])) if all(k in rows[s] for s in seeds) else "–"
                 for k, _ in task.rates]
        spent = np.mean([rows[s]["train_s"] for s in seeds])
        settings = rows[seeds[0]].get("policy")
        short = ", ".join(f"{k.split('.')[-1]}={v}" for k, v in (settings or {}).items())
        label = f"{m} ({short})" if settings else m
        print(f"| {label} | {','.join(map(str, seeds))} | " + " | ".join(cells) + f" | {spent:.0f} |")
        for k, label in task.rates:
            if all(k in rows[s] for s in seeds):
                print(f"    {label} per seed: " + " / ".join(f"{100 * rows[s][k]:.1f}" for s in seeds))
    ref_name, ref = args.methods[0], table[args.methods[0]]
    for m in args.methods[1:]:
        common = sorted(set(ref) & set(table[m]))
        if len(common) < 2:
            continue
        for key, label in task.rates:
            if all(key in table[m][s] and key in ref[s] for s in common):
                ci = t_interval([table[m][s][key] - ref[s][key] for s in common], bounds=None)
                print(f"{m} - {ref_name}, {label} (paired over seeds {common}): "
                      f"{format_ci(ci).replace(' %', ' points')}")


if __name__ == "__main__":
    main()
