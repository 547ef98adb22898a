"""What ``train.target_steps`` costs a cycle: lazy Q's ``run_cycle`` (targets of all rows, then
one epoch of Adam, the maze's default cycle) on a pointmaze run's first seed, its data and
neighbourhoods, for each number of steps in one process, alternating, median of
``--repeats`` after one compiling call each.

    .venv/bin/python experiments/bench_target_steps.py runs/pm_lazy_s0 --steps 1 10 25 --repeats 3
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import time

import jax
import numpy as np

from lazyq_jax import agents
from lazyq_jax.run.runner import load_run


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run_dir")
    p.add_argument("--method", default="lazy")
    p.add_argument("--steps", type=int, nargs="+", default=[1, 10, 25])
    p.add_argument("--repeats", type=int, default=3)
    args = p.parse_args()
    loaded = load_run(args.run_dir, args.method)
    base, seed = loaded.agent, loaded.seeds[0]
    n = int(loaded.data.n_valid[0])
    data = loaded.data.seed_data(0)
    t = time.perf_counter()
    nb = base.prepare(seed, data, n, 0)
    print(f"{n} rows; neighbourhoods {time.perf_counter() - t:.1f} s", flush=True)
    runs = {}
    for h in args.steps:
        train = dataclasses.replace(base.config.train, target_steps=h)
        agent = agents.make("lazy", dataclasses.replace(base.config, train=train), problem=base.problem)
        state = agent.trainer.init(jax.random.PRNGKey(seed), data)
        cycle = jax.jit(agent.trainer.run_cycle)
        t = time.perf_counter()
        jax.block_until_ready(cycle(state, data, nb.idx, None, nb.weights))
        print(f"target_steps={h}: first call (compile + run) {time.perf_counter() - t:.1f} s", flush=True)
        runs[h] = (cycle, state)
    times = {h: [] for h in args.steps}
    for _ in range(args.repeats):
        for h, (cycle, state) in runs.items():
            t = time.perf_counter()
            jax.block_until_ready(cycle(state, data, nb.idx, None, nb.weights))
            times[h].append(time.perf_counter() - t)
    out = {h: {"median_s": statistics.median(ts), "all_s": [round(x, 3) for x in ts]} for h, ts in times.items()}
    for h, r in out.items():
        print(f"target_steps={h}: {r['median_s']:.3f} s a cycle (median; {r['all_s']})")
    print(json.dumps({"run_dir": args.run_dir, "rows": n, "epochs": base.config.train.epochs,
                      "cycle_s": {str(h): r["median_s"] for h, r in out.items()},
                      "devices": [str(d) for d in jax.devices()], "numpy": np.__version__}))


if __name__ == "__main__":
    main()
