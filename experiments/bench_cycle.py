"""Benchmark: what one pointmaze training cycle of lazy Q spends, and the local fits solved
every cycle (``projection=None``) against their projection computed once (the default).

On OGBench's pointmaze-medium-navigate data of seed 0 at the paper preset (1M rows, k = 20
neighbours, the ``action+state+goal`` local model: 7 coefficients a fit, 10-step targets), in
one process, the two cycles taking turns (``_common.alternating``) so that a shared machine
slows both alike; then the parts of a cycle timed alone: the value table (Eq. 6's bracket,
one network pass over the rows), the fits with and without the projection, one epoch of
Adam (Eq. 10), and the projection itself (once per neighbourhood set).

    .venv/bin/python experiments/bench_cycle.py [--repeats 5] [--data /tmp/pm0.npz]

``--data``: where the collected rows are cached (collected on first use, ~1 min).
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from _common import alternating, timed  # the script's own folder is on sys.path

from lazyq_jax import agents, tasks
from lazyq_jax import train as T
from lazyq_jax.agents.lazy import LazyConfig
from lazyq_jax.targets import multi_step_transitions
from lazyq_jax.types import Transitions


def dataset(path: Path, task, config) -> Transitions:
    if path.exists():
        with np.load(path) as f:
            return Transitions(**{k: f[k] for k in f.files})
    data = task.collect(jax.random.PRNGKey(0), config, progress=True)
    np.savez(path, **{k: np.asarray(v) for k, v in vars(data).items() if v is not None})
    return data


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--data", type=Path, default=None,
                    help="the data's cache file (default /tmp/lazyq_bench_<task>_<episodes>.npz)")
    ap.add_argument("--task", default="pointmaze", help="a pointmaze dataset's task (default medium navigate)")
    ap.add_argument("--episodes", type=int, default=None, help="fewer episodes (a quick look)")
    args = ap.parse_args()
    task, config = tasks.get(args.task), tasks.preset(args.task)
    if args.episodes:
        config = dataclasses.replace(config, collect=dataclasses.replace(config.collect,
                                                                        episodes=args.episodes))
    cache = args.data or Path(f"/tmp/lazyq_bench_{args.task}_{config.collect.episodes}.npz")
    data = jax.tree.map(jnp.asarray, dataset(cache, task, config))
    agent = agents.make("lazy", LazyConfig(train=config.train, neighbours=config.neighbours),
                        problem=task.problem(config))
    aux = agent.prepare(0, data, data.size, 0)
    state = agent.init(jax.random.PRNGKey(1), data)
    setup = agent.trainer.run_cycle.args[0]
    tc = config.train
    paths, gamma = jax.jit(lambda d: multi_step_transitions(d, tc.target_steps, tc.gamma))(data)

    cycle = jax.jit(lambda st, p: T._run_cycle(setup, st, data, aux.idx, None, None, p))
    project = jax.jit(lambda: T._projection(setup, data, aux.idx))
    fits = jax.jit(lambda st, p: T._local_fits(setup, st, paths, gamma, aux.idx, None, p))
    table = jax.jit(lambda st: T.bootstrap_table(T._value_fn(setup, st), paths, gamma,
                                                 tc.target_batch_size))
    epoch = jax.jit(lambda st, y, k: T._epoch(setup, st, data, y, k))
    proj, proj_first, proj_s = timed(project, repeats=1)
    print(f"rows {data.size}, k {aux.idx.shape[1]}, projection {proj.shape} "
          f"({proj.size * 4 / 2**20:.0f} MiB): first {proj_first:.2f} s, then {proj_s:.2f} s")
    for name, fn in (("solved every cycle", lambda: cycle(state, None)), ("projection", lambda: cycle(state, proj))):
        first = timed(fn, repeats=1)[1]
        print(f"cycle, {name}: first call {first:.2f} s")
    times = alternating({"solved every cycle": lambda: cycle(state, None),
                         "projection": lambda: cycle(state, proj)}, args.repeats)
    print(f"\n| one cycle ({args.repeats} alternating repeats, median) | s |\n|---|---|")
    for name, t in times.items():
        print(f"| {name} | {statistics.median(t):.3f} |")
    y = jnp.zeros(data.size, jnp.float32)
    key = jax.random.PRNGKey(2)
    parts = {"value table (Eq. 6's bracket, 1 network pass)": lambda: table(state),
             "fits solved (Eq. 5-6, value table included)": lambda: fits(state, None),
             "fits from the projection (value table included)": lambda: fits(state, proj),
             "one epoch of Adam (Eq. 10)": lambda: epoch(state, y, key)}
    for fn in parts.values():
        jax.block_until_ready(fn())
    times = alternating(parts, args.repeats)
    print(f"\n| part of a cycle | s |\n|---|---|")
    for name, t in times.items():
        print(f"| {name} | {statistics.median(t):.3f} |")


if __name__ == "__main__":
    main()
