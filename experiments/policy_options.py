"""Acting options of trained lazy Q runs against each other: the same checkpoints, datasets and
evaluation episodes, only how the policy acts changes (``lazyq_jax.config.POLICY_FIELDS``:
options of the policy step, not of training; ``evaluate --set`` changes them for a whole
run).  Trains nothing.

For each value of ``--option`` every run directory's lazy Q is evaluated again by its task
(the run's own evaluation keys); the table gives the mean [95 % CI] over all seeds of all
directories, the run's stored ``eval.json`` beside them (the code it was evaluated with), and
each row's paired difference to the first value.  The idle steps (zero actions: where the
policy has no model that prefers an action and acts with the zero action) are counted too.

    .venv/bin/python experiments/policy_options.py \\
        runs/arm_levers/arm-long/fingertip_offsets_box0.6_disk0.3_x4 \\
        runs/arm_levers_s34/arm-long/fingertip_offsets_box0.6_disk0.3_x4 \\
        --option neighbours.no_model_action --values zero random
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from _common import rate_keys, rates_table  # the script's own folder is on sys.path

from lazyq_jax import tasks
from lazyq_jax.config import POLICY_FIELDS
from lazyq_jax.run import load_run
from lazyq_jax.run.runner import open_existing


def idle_steps(result: dict) -> int:
    """The zero actions of one seed's evaluation, over its protocols."""
    return sum(int(v.get("idle_steps", 0)) for v in result.values() if isinstance(v, dict))


def evaluate_with(run_dir: Path, option: str, value: str) -> list[dict]:
    """Every seed of ``run_dir``'s lazy Q evaluated with ``option=value`` (an acting option:
    the trained states are the run's)."""
    loaded = load_run(run_dir, "lazy", overrides=[f"{option}={value}"])
    agent = loaded.agent
    policies = agent.policies(loaded.states, loaded.data.stacked, loaded.data.n_valid)
    ev = loaded.task.evaluate(agent.act, policies, loaded.config, loaded.seeds)
    rows = []
    for result in ev.per_seed:
        rates = loaded.task.seed_rates(result)
        rows.append({"run": str(run_dir), "seed": result["seed"], **rates, "idle_steps": idle_steps(result)})
    return rows


def stored_rows(run_dir: Path) -> list[dict]:
    """The run's own ``lazy/eval.json`` as rows (the code it was evaluated with)."""
    task = tasks.get(open_existing(run_dir)[0].task)  # the task only: no data, no checkpoint
    stored = json.loads((run_dir / "lazy" / "eval.json").read_text())["per_seed"]
    return [{"run": str(run_dir), "seed": r["seed"], **task.seed_rates(r), "idle_steps": idle_steps(r)}
            for r in stored]


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run_dirs", type=Path, nargs="+")
    ap.add_argument("--option", choices=POLICY_FIELDS, default="neighbours.no_model_action")
    ap.add_argument("--values", nargs="+", default=["zero", "random"])
    ap.add_argument("--out", type=Path, help="JSON file (default: FIRST_RUN_DIR/policy_options.json)")
    args = ap.parse_args()
    table = {}
    for value in args.values:
        t = time.perf_counter()
        table[f"{args.option}={value}"] = [row for d in args.run_dirs for row in evaluate_with(d, args.option, value)]
        print(f"{args.option}={value}: evaluated in {time.perf_counter() - t:.0f} s", flush=True)
    table["stored eval.json"] = [row for d in args.run_dirs for row in stored_rows(d)]
    out = args.out or args.run_dirs[0] / "policy_options.json"
    out.write_text(json.dumps(table, indent=1))
    keys = rate_keys(table[next(iter(table))][0])
    print(f"\n{len(table['stored eval.json'])} seeds ({', '.join(str(d) for d in args.run_dirs)}); "
          "mean [95 % CI]; last column: idle steps summed")
    rates_table(table, keys, extra=lambda rows: str(sum(r["idle_steps"] for r in rows)), head="acting")
    for name, rows in table.items():
        print(f"{name}: per seed " + "; ".join(
            f"{r['seed']}: " + " / ".join(f"{100 * r[k]:.1f}" for k in keys) for r in rows))


if __name__ == "__main__":
    main()
