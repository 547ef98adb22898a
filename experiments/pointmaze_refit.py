"""Does a closer regression move lazy Q's converged V towards V*?  Value iteration continued
from a trained pointmaze run with other training settings (e.g. more epochs a cycle), with
V against the walls-aware optimum V* measured as it goes.

With gamma = 0.99 a systematic error e a backup moves the fixed point by up to e / (1 - gamma);
one epoch a cycle leaves the regression's loss at 0.26-0.95 (an RMS of 0.5-1.0 a target).  This
script takes a run's trained state (its first seed), its data and its neighbourhoods, and runs
``--cycles`` more cycles of ``agent.run_block`` with ``--set`` overrides of its ``train`` section
(``--set epochs=5``), reporting every ``--every`` cycles the mean of ``V - V*`` on all scored
rows and on the wall pairs (pointmaze_oracle.py's rows, 200,000 by default) and Spearman's rank
correlation of V with V* and with the straight-line value on the wall pairs.  The run
directory is only read.

    .venv/bin/python experiments/pointmaze_refit.py runs/pm_row_s0 --cycles 50 --every 10 \\
        --set epochs=5
    .venv/bin/python experiments/pointmaze_refit.py runs/pm_row_s0 --cycles 50 --every 10   # control
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from scipy.stats import spearmanr

from lazyq_jax import agents
from lazyq_jax.config import override
from lazyq_jax.run import load_run
from lazyq_jax.targets import evaluate_in_batches
from lazyq_jax.tasks.pointmaze.maze import get_maze

sys.path.insert(0, str(Path(__file__).parent))
from pointmaze_oracle import scored_rows  # noqa: E402
from pointmaze_walls import Geodesic, value_of  # noqa: E402


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("run_dir")
    p.add_argument("--cycles", type=int, default=50)
    p.add_argument("--every", type=int, default=10)
    p.add_argument("--pairs", type=int, default=200000)
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="an override of the run's train section, e.g. epochs=5")
    p.add_argument("--out", default=None, help="a JSON file for the measurements")
    args = p.parse_args()
    loaded = load_run(args.run_dir, "lazy")
    config = override(loaded.config, [f"train.{s}" for s in args.set])
    if config.task != "pointmaze":
        raise SystemExit(f"{args.run_dir} is a {config.task} run, not pointmaze")
    agent = agents.make("lazy", agents.LazyConfig(train=config.train, neighbours=config.neighbours),
                        problem=loaded.task.problem(config))
    seed, n = loaded.seeds[0], int(loaded.data.n_valid[0])
    data = loaded.data.seed_data(0)
    gamma = config.train.gamma
    s, g = np.asarray(data.s[:n]), np.asarray(data.g[:n])
    geo = Geodesic(get_maze(config.collect.maze))
    rows, v_star, wall = scored_rows(np.random.default_rng(0), args.pairs, s, g, geo, gamma)
    v_line = value_of(np.abs(s[rows] - g[rows]).max(1), gamma)
    t = time.perf_counter()
    aux = agent.prepare(seed, data, n, 0)
    print(f"neighbourhoods: {time.perf_counter() - t:.0f} s", flush=True)
    state = loaded.state()  # parameters, batch statistics and Adam's moments as the run left them
    run_block = jax.jit(agent.run_block)
    out = {"run_dir": args.run_dir, "set": args.set, "points": []}

    def measure(cycle, loss):
        v = np.asarray(evaluate_in_batches(agent.value_fn(state), jnp.asarray(s[rows]), jnp.asarray(g[rows]),
                                           65536), np.float64)
        e = v - v_star
        point = {"cycle": cycle, "loss": loss, "gap_all": float(e.mean()), "gap_wall": float(e[wall].mean()),
                 "wall_rho_star": float(spearmanr(v[wall], v_star[wall]).statistic),
                 "wall_rho_line": float(spearmanr(v[wall], v_line[wall]).statistic)}
        out["points"].append(point)
        print(json.dumps(point), flush=True)

    measure(0, None)
    n_valid = jnp.int32(n)
    for c in range(1, args.cycles + 1):
        t = time.perf_counter()
        state, metrics = run_block(state, data, aux, n_valid)
        loss = float(metrics["loss"])
        print(f"cycle {c}: loss {loss:.4f} ({time.perf_counter() - t:.1f} s)", flush=True)
        if c % args.every == 0:
            measure(c, loss)
    if args.out:
        Path(args.out).write_text(json.dumps(out, indent=1))
        print(f"-> {args.out}")


if __name__ == "__main__":
    main()
