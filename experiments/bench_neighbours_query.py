"""The policy's per-step neighbour query in general spaces: the scan of all data
(:func:`lazyq_jax.neighbours.query.query_neighbours_scan`, the old path) against the
policy index (:func:`~lazyq_jax.neighbours.query.build_policy_index` +
:func:`~lazyq_jax.neighbours.query.query_policy`), in the same run, on data like the arm
task's: ``n_states`` states uniform in a box of half-widths (pi/2, 2.5, 2.5, [0.5, 0.5])
(d_s = 3 joint angles, or 5 with the disk position), each relabelled with ``goals`` random
angle goals (N = n_states * goals), radius_s 0.12, radius_g 0.1, k = 20, growth 2^(1/3),
max_level 5; queries: a batch of ``batch`` (protocol A's 320 episodes) states uniform in
the same box with random goals, compiled, best of ``repeats`` (old and new interleaved,
so that a shared machine slows both alike).  The scan runs on the first ``scan_queries``
of the batch (it costs ~11 ms a query); both results are checked to agree there (levels
and counts; the samples are different uniform draws).

    .venv/bin/python experiments/bench_neighbours_query.py [--n-states 10000] [--goals 100]
        [--dims 3 5] [--batch 320] [--scan-queries 32] [--repeats 3]

Measured (2 CPU cores shared with two other engineers' jobs, load average 4-5; N =
1,000,000; four runs gave 100-128x for d_s = 3 and 88-106x for d_s = 5), the last run:

    d_s  scan ms/query  policy ms/query  ratio  build s  compile s  MB (scan)  phases lo-hi:slots x items
    3    13.00          0.130            100    0.70     6.8        22 (15)    0-4:320x56+5-5:16x88
    5    12.66          0.144            88     0.64     4.5        28 (23)    0-5:320x90

("compile s": the first call of the jitted batch, compile included; the policy index
answers every query of these batches within its capacities: overflow 0.  Levels of the
320 queries: d_s = 3 mostly 2-3, d_s = 5 mostly 5 and 68 beyond max_level.)
"""

from __future__ import annotations

import argparse
import time

import jax
import numpy as np

from lazyq_jax.neighbours.query import build_policy_index, build_scan_index, query_neighbours_scan, query_policy

HALF_WIDTHS = (np.pi / 2, 2.5, 2.5, 0.5, 0.5)
PARAMS = {"k": 20, "radius_s": 0.12, "radius_g": 0.1, "growth": 2 ** (1 / 3), "max_level": 5}


def arm_like(rng, d_s: int, n_states: int, goals: int, batch: int):
    hw = np.asarray(HALF_WIDTHS[:d_s], np.float32)
    states = rng.uniform(-hw, hw, (n_states, d_s)).astype(np.float32)
    s = np.repeat(states, goals, axis=0)
    g = rng.uniform(-np.pi, np.pi, s.shape[0]).astype(np.float32)
    qs = rng.uniform(-hw, hw, (batch, d_s)).astype(np.float32)
    qg = rng.uniform(-np.pi, np.pi, batch).astype(np.float32)
    return s, g, qs, qg


def timed(fn, *args):
    t = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    return time.perf_counter() - t, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n-states", type=int, default=10_000)
    ap.add_argument("--goals", type=int, default=100)
    ap.add_argument("--dims", type=int, nargs="+", default=[3, 5])
    ap.add_argument("--batch", type=int, default=320)
    ap.add_argument("--scan-queries", type=int, default=32)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    n = args.n_states * args.goals
    print(f"backend {jax.default_backend()}, {jax.device_count()} device(s), N = {n:,}, batch {args.batch}, "
          f"scan on {args.scan_queries} of them", flush=True)
    rows = []
    for d in args.dims:
        s, g, qs, qg = arm_like(rng, d, args.n_states, args.goals, args.batch)
        scan_index = build_scan_index(s, g, **PARAMS)
        t = time.perf_counter()
        stats = {}
        index = build_policy_index(s, g, **PARAMS, stats=stats)
        build_s = time.perf_counter() - t
        m = args.scan_queries
        old, new = jax.jit(query_neighbours_scan), jax.jit(query_policy)  # the index an argument
        compile_old, _ = timed(old, scan_index, jax.random.PRNGKey(0), qs[:m], qg[:m])
        compile_new, _ = timed(new, index, jax.random.PRNGKey(0), qs, qg)
        best_old = best_new = float("inf")
        for r in range(args.repeats):
            t_old, nb_old = timed(old, scan_index, jax.random.PRNGKey(r + 1), qs[:m], qg[:m])
            t_new, nb_new = timed(new, index, jax.random.PRNGKey(r + 1), qs, qg)
            best_old, best_new = min(best_old, t_old), min(best_new, t_new)
        for a, b in ((nb_old.level, nb_new.level[:m]), (nb_old.count, nb_new.count[:m])):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
        old_ms, new_ms = 1e3 * best_old / m, 1e3 * best_new / args.batch
        level = np.asarray(nb_new.level)
        mb = sum(x.nbytes for x in jax.tree.leaves(index)) / 2**20
        mb_scan = sum(x.nbytes for x in jax.tree.leaves(scan_index)) / 2**20
        rows.append((d, old_ms, new_ms, old_ms / new_ms, build_s, compile_new, mb, mb_scan,
                     "+".join(f"{p.lo}-{p.hi}:{p.slots(args.batch)}x{p.cap}" for p in index.phases)))
        print(f"d_s = {d}: scan {old_ms:.2f} ms a query, policy index {new_ms:.3f} ms a query "
              f"(batch {args.batch}): {old_ms / new_ms:.0f}x; index build {build_s:.2f} s, compile "
              f"{compile_new:.1f} s (scan {compile_old:.1f} s); memory {mb:.0f} MB (scan {mb_scan:.0f} MB); "
              f"overflow {int(np.sum(nb_new.overflow))}; "
              f"levels -1..{PARAMS['max_level']}: {np.bincount(level + 1, minlength=PARAMS['max_level'] + 2)}; "
              f"grid cols {[ax.col for ax in index.grid]}, widths "
              f"{[round(ax.width, 4) for ax in index.grid]}; phases lo-hi:slots x items {rows[-1][-1]}",
              flush=True)
    print("\n    d_s  scan ms/query  policy ms/query  ratio  build s  compile s  MB (scan)  phases lo-hi:slots x items")
    for d, o, nw, ratio, b, c, mb, mbs, ph in rows:
        print(f"    {d:<4} {o:<14.2f} {nw:<16.3f} {ratio:<6.0f} {b:<8.2f} {c:<10.1f} {f'{mb:.0f} ({mbs:.0f})':<10} {ph}")


if __name__ == "__main__":
    main()
