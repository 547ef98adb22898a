"""OGBench's pointmaze at an equal CPU budget: lazy Q and the goal-conditioned baselines on the
same data, seeds and evaluation, each trained for the same wall-clock time on this machine.

1. ``study --task pointmaze --methods lazy`` (the task's ``paper`` preset, or ``--set``
   overrides): its training seconds (``lazy/timings.json``, neighbour search included) are the
   budget, unless ``--seconds`` gives one.
2. Each baseline's gradient steps per second at OGBench's settings (3 x 512, batch 1024) on
   this machine: one block of ``--calibrate`` steps after compilation, on seed 0's dataset,
   all seeds vmapped as in the study.
3. The baselines trained for ``budget x steps/s`` steps into the same run directory
   (``--resume``: finished methods are kept); ``python -m lazyq_jax report RUN_DIR`` then
   writes the table.

    .venv/bin/python experiments/pointmaze_budget.py --run-dir runs/pointmaze_budget --seeds 1
    .venv/bin/python experiments/pointmaze_budget.py --run-dir R --seconds 600 --methods gcivl,gcbc
    .venv/bin/python experiments/pointmaze_budget.py --run-dir R --seeds 3 --methods gcivl --max-seconds 150

OGBench trains 1M steps of batch 1024; the fraction of that budget each baseline got is printed
and kept in ``RUN_DIR/budget.json``.  Results: docs/pointmaze.md.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax

from lazyq_jax import agents, tasks
from lazyq_jax.config import override
from lazyq_jax.run import run
from lazyq_jax.run.sources import static_data

OGBENCH_STEPS = 1_000_000


def steps_per_second(spec: str, config, task, sd, calibrate: int) -> float:
    """Gradient steps per second of baseline ``spec`` (``name[:field=value...]``) with the
    task's settings and the spec's options, all seeds, compiled as the runner compiles it."""
    name, *options = spec.split(":")
    cls = agents.config_class(name)
    cfg = cls(steps=calibrate, blocks=1, gamma=config.train.gamma, **task.method_defaults(name))
    cfg = override(cfg, options)
    agent = agents.make(name, cfg, problem=task.problem(config))
    data, n_valid = sd.stacked, sd.n_valid
    keys = jax.random.split(jax.random.PRNGKey(0), len(n_valid))
    init = jax.jit(jax.vmap(agent.init))
    block = jax.jit(jax.vmap(lambda st, d, n: agent.run_block(st, d, None, n)))
    if len(n_valid) == 1:  # as the runner: one seed runs unbatched (a vmap of 1 ran 2x slower)
        data, n_valid, keys = jax.tree.map(lambda x: x[0], (data, n_valid, keys))
        init, block = jax.jit(agent.init), jax.jit(lambda st, d, n: agent.run_block(st, d, None, n))
    state = init(keys, data)
    jax.block_until_ready(block(state, data, n_valid))  # compile
    t = time.perf_counter()
    jax.block_until_ready(block(state, data, n_valid))
    return calibrate / (time.perf_counter() - t)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--run-dir", default="runs/pointmaze_budget")
    p.add_argument("--seeds", type=int, default=1)
    p.add_argument("--methods", default="gcivl,gciql,gcbc",
                   help="baselines, each with options if wanted (gcivl:width=128)")
    p.add_argument("--seconds", type=float, default=None, help="budget (default: lazy Q's training time)")
    p.add_argument("--max-seconds", type=float, default=None,
                   help="cap on the budget (a lent device's minutes); the table says when it bound")
    p.add_argument("--preset", default="paper", help="the task's preset (smoke: a tiny end-to-end check)")
    p.add_argument("--calibrate", type=int, default=200,
                   help="steps timed per baseline (after compiling)")
    p.add_argument("--calibrate-only", action="store_true", help="print the rates, train nothing")
    p.add_argument("--set", action="append", default=[], dest="sets", metavar="FIELD=VALUE")
    args = p.parse_args()
    run_dir = Path(args.run_dir)
    seeds = list(range(args.seeds))
    config = override(tasks.preset("pointmaze", args.preset), args.sets)
    task = tasks.get("pointmaze")

    if args.seconds is None:
        run(config, run_dir, seeds=seeds, methods=["lazy"], resume=True, progress=False)
        lazy_timing = json.loads((run_dir / "lazy" / "timings.json").read_text())
        # lazy Q's training time includes its neighbour search and its first cycle's
        # compilation; the baselines get that many seconds of compiled steps
        budget = lazy_timing["train_s"] + lazy_timing.get("prepare_s", 0.0)
    else:
        budget = args.seconds
    capped = args.max_seconds is not None and budget > args.max_seconds
    if capped:
        print(f"budget {budget:.0f} s capped at --max-seconds {args.max_seconds:.0f} s: the baselines "
              "get less time than lazy Q")
        budget = args.max_seconds
    print(f"budget: {budget:.0f} s of training per method ({len(seeds)} seed(s) together)")

    sd = static_data(task, config, run_dir, seeds, progress=False)
    specs, fractions = [], {}
    for spec in args.methods.split(","):
        rate = steps_per_second(spec, config, task, sd, args.calibrate)
        steps = max(1, int(budget * rate))
        fractions[spec] = steps / OGBENCH_STEPS
        print(f"{spec}: {rate:.2f} steps/s -> {steps} steps ({fractions[spec]:.2%} of OGBench's 1M)",
              flush=True)
        specs.append(f"{spec}:steps={steps}")
    if args.calibrate_only:
        return
    (run_dir / "budget.json").write_text(json.dumps(
        {"budget_s": budget, "capped": capped, "calibrate_steps": args.calibrate, "specs": specs,
         "ogbench_fraction": fractions}, indent=1))
    # with --seconds lazy Q need not be in this run directory (nor is it trained here)
    methods = specs if args.seconds is not None else ["lazy", *specs]
    run(config, run_dir, seeds=seeds, methods=methods, resume=True, progress=False)

    print(f"the table: .venv/bin/python -m lazyq_jax report {run_dir}")

if __name__ == "__main__":
    main()
