"""The policy's per-step neighbour query in the paper's space (2-D states, angle goals):
the grid's query (:func:`lazyq_jax.neighbours.grid.query_neighbours`, the lazy policy's
path there until now) against the general policy index
(:func:`~lazyq_jax.neighbours.query.build_policy_index` +
:func:`~lazyq_jax.neighbours.query.query_policy`), in the same run, on two datasets made
by the tasks themselves (seed 0):

* ``push``: the paper's push task (the ``paper`` preset: 5000 episodes, ~1M rows, the
  finger's position relative to the disk; k = 20, radius_s 0.06, radius_g 0.1,
  max_level 5, the task's search bounds);
* ``arm-long-w0``: arm-long's data in the 2-D feature map "fingertip - disk" alone
  (``neighbours.feature_weight=0``; max_level 10): ~1M rows in a much denser 2-D space,
  where the grid's static window (the stencil of ``max_level`` for every query) is large.

Queries: ``batch`` rows of the dataset (a policy's states lie where the data are) moved
by N(0, radius_s) in each coordinate, with uniform angle goals; compiled first, then the
best of ``repeats`` (the two interleaved, so that a shared machine slows both alike).
Both are exact searches with the same semantics: their levels and counts are checked to
be equal on every query (the samples are different uniform draws).

    .venv/bin/python experiments/bench_policy_2d.py [--spaces push arm-long-w0] [--batch 320]
"""

from __future__ import annotations

import argparse
import math
import time

import jax
import numpy as np
from bench_neighbours_query import timed  # the script's own folder is on sys.path

from lazyq_jax import tasks
from lazyq_jax.config import override
from lazyq_jax.neighbours import build_index, query_neighbours
from lazyq_jax.neighbours.grid import W, _stencil
from lazyq_jax.neighbours.query import build_policy_index, query_policy

SPACES = {"push": ("push", []),
          "arm-long-w0": ("arm-long", ["neighbours.features=fingertip", "neighbours.feature_weight=0"])}


def dataset(space: str):
    name, sets = SPACES[space]
    task = tasks.get(name)
    config = override(tasks.preset(name, "paper"), sets)
    problem = task.problem(config)
    data = task.collect(jax.random.PRNGKey(0), config)
    x = np.asarray(data.s) if problem.features is None else np.asarray(jax.jit(problem.features)(data.s))
    return x.astype(np.float32), np.asarray(data.g, np.float32), config.neighbours, problem.search_bounds


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--spaces", nargs="+", default=list(SPACES), choices=list(SPACES))
    ap.add_argument("--batch", type=int, default=320)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    print(f"backend {jax.default_backend()}, {jax.device_count()} device(s), batch {args.batch}", flush=True)
    rows = []
    for space in args.spaces:
        x, g, nc, bounds = dataset(space)
        params = {"k": nc.k, "radius_s": nc.radius_s, "radius_g": nc.radius_g, "growth": nc.growth,
                  "max_level": nc.max_level}
        rng = np.random.default_rng(1)
        pick = rng.integers(0, x.shape[0], args.batch)
        qs = (x[pick] + rng.normal(0, nc.radius_s, (args.batch, 2))).astype(np.float32)
        if bounds is not None:  # the grid's bounds are the task's: queries stay inside
            qs = np.clip(qs, bounds[:2], bounds[2:]).astype(np.float32)
        qg = rng.uniform(-np.pi, np.pi, args.batch).astype(np.float32)
        t = time.perf_counter()
        grid = build_index(x, g, **params, bounds=bounds)
        grid_build = time.perf_counter() - t
        t = time.perf_counter()
        index = build_policy_index(x, g, **params)
        index_build = time.perf_counter() - t
        old, new = jax.jit(query_neighbours), jax.jit(query_policy)  # the index an argument
        compile_old, _ = timed(old, grid, jax.random.PRNGKey(0), qs, qg)
        compile_new, _ = timed(new, index, jax.random.PRNGKey(0), qs, qg)
        best_old = best_new = float("inf")
        for r in range(args.repeats):
            t_old, nb_old = timed(old, grid, jax.random.PRNGKey(r + 1), qs, qg)
            t_new, nb_new = timed(new, index, jax.random.PRNGKey(r + 1), qs, qg)
            best_old, best_new = min(best_old, t_old), min(best_new, t_new)
        for a, b in ((nb_old.level, nb_new.level), (nb_old.count, nb_new.count)):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
        _, _, n_rows, n_blocks, _ = _stencil(grid, grid.max_level)
        grid_items = n_rows * n_blocks * math.ceil(grid.max_window / W)
        old_ms, new_ms = 1e3 * best_old / args.batch, 1e3 * best_new / args.batch
        level = np.asarray(nb_new.level)
        phases = "+".join(f"{p.lo}-{p.hi}:{p.slots(args.batch)}x{p.cap}" for p in index.phases)
        rows.append((space, x.shape[0], old_ms, new_ms, old_ms / new_ms, grid_items, phases,
                     compile_old, compile_new, grid_build, index_build))
        print(f"{space}: N = {x.shape[0]:,}; grid {old_ms:.3f} ms a query ({grid_items} items of {W} a "
              f"query), policy index {new_ms:.3f} ms ({phases}): {old_ms / new_ms:.1f}x; compile "
              f"{compile_old:.1f} / {compile_new:.1f} s; build {grid_build:.2f} / {index_build:.2f} s; "
              f"overflow {int(np.sum(nb_new.overflow))}; levels -1..{nc.max_level}: "
              f"{np.bincount(level + 1, minlength=nc.max_level + 2)}", flush=True)
    print("\n    space         N          grid ms/query  index ms/query  ratio  grid items/query  index phases lo-hi:slots x items")
    for sp, n, o, nw, ratio, gi, ph, *_ in rows:
        print(f"    {sp:<13} {n:<10,} {o:<14.3f} {nw:<15.3f} {ratio:<6.1f} {gi:<17} {ph}")


if __name__ == "__main__":
    main()
