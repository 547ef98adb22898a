"""The lazy policy's neighbour-index layouts of a run's seeds, their stack, and the compile
time of the stacked query (the per-step program of an evaluation, seeds vmapped).

Each seed's data choose their own layout (grid axes, query phases and capacities: the cost
model of ``lazyq_jax.neighbours.query``); ``stack_policy_indices`` lays every seed out on the
first seed's.  Prints each layout, the stacked one and the items a batch of 320 queries
reads, then compiles ``jit(vmap(query_policy))`` for the stack in the seeds' order and with
the second seed first (the order decides the layout).

    .venv/bin/python experiments/policy_layouts.py runs/arm_levers/arm/fingertip_offsets_x4_g25 --seeds 0,1,2,3,4
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import jax.numpy as jnp
import numpy as np

from lazyq_jax import agents, tasks
from lazyq_jax.agents.lazy import LazyConfig
from lazyq_jax.data import load_dataset
from lazyq_jax.neighbours.query import query_policy, stack_policy_indices
from lazyq_jax.policy import policy_index

BATCH = 320  # the arm's protocol A: 16 directions x 20 episodes


def describe(ix) -> str:
    grid = [(a.col, a.block, a.n, round(a.width, 4)) for a in ix.grid]
    phases = [(p.lo, p.hi, round(p.frac, 3), p.cap) for p in ix.phases]
    items = sum(p.slots(BATCH) * p.cap for p in ix.phases)
    return f"grid (col, block, cells, width) {grid}; phases (lo, hi, frac, cap) {phases}; items a batch {items}"


def compile_seconds(stacked) -> float:
    n_seeds = stacked.n_entries.shape[0]
    f = jax.jit(jax.vmap(lambda ix, k, s, g: query_policy(ix, k, s, g)))
    s = jnp.zeros((n_seeds, BATCH, stacked.d_s), jnp.float32)
    g = None if stacked.goal == "none" else jnp.zeros((n_seeds, BATCH) + ((stacked.d_g,) if stacked.goal == "vector" else ()),
                                                      jnp.float32)
    keys = jax.random.split(jax.random.key(0), n_seeds)
    t = time.perf_counter()
    f.lower(stacked, keys, s, g).compile()
    return time.perf_counter() - t


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("run", help="a run directory with data/<seed>/dataset.npz and run.json")
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--rotated-first", action="store_true",
                    help="compile the stack with the second seed first before the seeds' own order "
                         "(when one order's program may take long to compile, e.g. on a GPU)")
    args = ap.parse_args()
    seeds = [int(x) for x in args.seeds.split(",")]
    cfg = tasks.config_from_dict(json.load(open(f"{args.run}/run.json"))["config"])
    agent = agents.make("lazy", LazyConfig(train=cfg.train, neighbours=cfg.neighbours),
                        problem=tasks.get(cfg.task).problem(cfg))
    nc = cfg.neighbours
    datas = [load_dataset(f"{args.run}/data/{s}/dataset.npz")[0] for s in seeds]
    n_rows = max(len(d.s) for d in datas)  # the runner pads the seeds' datasets to one length

    def pad(a):
        return np.concatenate([a, np.repeat(a[-1:], n_rows - len(a), axis=0)])

    indices = []
    for seed, data in zip(seeds, datas):
        g = None if data.g is None else pad(np.asarray(data.g))
        t = time.perf_counter()
        ix = policy_index(pad(agent.search_space(np.asarray(data.s))), g, k=nc.k, radius_s=nc.radius_s,
                          radius_g=nc.radius_g, growth=nc.growth, max_level=nc.max_level,
                          n_valid=len(data.s))
        print(f"seed {seed}: {len(data.s):,} rows, built in {time.perf_counter() - t:.1f} s; {describe(ix)}")
        indices.append(ix)
    orders = [(seeds[0], indices), (seeds[1 % len(seeds)], indices[1:] + indices[:1])]
    for first, order in (orders[::-1] if args.rotated_first else orders):
        stacked = stack_policy_indices(order)
        print(f"stacked on seed {first}'s layout: {describe(stacked)}")
        print(f"  jit(vmap(query_policy)) compile, {len(seeds)} seeds x {BATCH} queries: "
              f"{compile_seconds(stacked):.1f} s ({jax.devices()[0].platform})", flush=True)


if __name__ == "__main__":
    main()
