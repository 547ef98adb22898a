"""The policy's per-step neighbour query in general spaces (lazyq_jax.neighbours_query):
milliseconds per query at N data points, uniform data with an angle goal, compiled,
for several state sizes and batch sizes (queries sharing one pass).

    .venv/bin/python experiments/bench_neighbours_query.py [--n 1000000] [--dims 3 5]
        [--batches 1 16] [--queries 100] [--repeats 3]

Prints one line per (d_s, batch): the best of ``repeats`` timings of ``queries`` queries.
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

from lazyq_jax.neighbours.query import build_scan_index, query_neighbours_scan


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=1_000_000)
    ap.add_argument("--dims", type=int, nargs="+", default=[3, 5])
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 16])
    ap.add_argument("--queries", type=int, default=100)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    print(f"backend {jax.default_backend()}, {jax.device_count()} device(s), N = {args.n:,}")
    for d in args.dims:
        s = rng.uniform(-1, 1, (args.n, d)).astype(np.float32)
        g = rng.uniform(-np.pi, np.pi, args.n).astype(np.float32)
        index = build_scan_index(s, g, k=20, radius_s=0.12, max_level=10)
        qs, qg = jnp.asarray(s[: args.queries]), jnp.asarray(g[: args.queries])
        for batch in args.batches:
            run = jax.jit(lambda key, b=batch: query_neighbours_scan(index, key, qs, qg, batch=b))
            jax.block_until_ready(run(jax.random.PRNGKey(0)))  # compile
            best = float("inf")
            for r in range(args.repeats):
                t = time.perf_counter()
                jax.block_until_ready(run(jax.random.PRNGKey(r + 1)))
                best = min(best, time.perf_counter() - t)
            print(f"d_s = {d}, batch {batch:>3}: {1e3 * best / args.queries:.1f} ms a query", flush=True)


if __name__ == "__main__":
    main()
