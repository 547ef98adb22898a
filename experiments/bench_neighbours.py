"""Benchmark: all-points neighbour search (paper §V-A-2) vs scipy cKDTree, same run.

Data like the paper's: ``N/100`` finger states uniform in ``[-1, 1]^2`` outside a
disk of radius 0.25 + 0.06, each paired with 100 goals uniform in ``[-pi, pi)``;
every data point is also a query (Q = N), as training needs. Prints compile time
and steady-state time (median, ``block_until_ready``) separately, and checks the
JAX result against brute force on a random subset of queries (level, count,
membership, distinctness).  ``--build host,device`` also times the other
``build_index`` (NumPy on the host, or one jitted program on JAX's default device) in the
same run and checks that both give bitwise the same index; the search uses the first.

    flock /tmp/lazyq_bench.lock .venv/bin/python experiments/bench_neighbours.py [--n 1000000] [--skip-scipy]
"""

from __future__ import annotations

import argparse
import time

import jax
import numpy as np

from lazyq_jax.neighbours import build_index, radius_tables, search_all, wrap_angle
from lazyq_jax.neighbours.common import TWO_PI

K, RS, RG, GROWTH = 20, 0.06, 0.1, 2 ** (1 / 3)


def paper_like_data(n, seed=0):
    rng = np.random.default_rng(seed)
    n_states = max(n // 100, 1)
    states = np.empty((0, 2))
    while len(states) < n_states:
        p = rng.uniform(-1, 1, (2 * n_states, 2))
        states = np.concatenate([states, p[np.linalg.norm(p, axis=1) > 0.31]])
    s = np.repeat(states[:n_states], 100, axis=0)[:n].astype(np.float32)
    g = rng.uniform(-np.pi, np.pi, len(s)).astype(np.float32)
    return s, g


def brute_level(s, g, q_s, q_g, k=K):
    """Per query: (level, |B_level|, membership level of every data point), float32 formula."""
    levels = np.arange(200)
    r2s, rg = radius_tables(RS, RG, GROWTH, levels)
    dx = s[:, 0] - q_s[0]
    dy = s[:, 1] - q_s[1]
    d = np.abs(wrap_angle(g) - wrap_angle(np.float32(q_g)))
    lam = np.maximum(np.searchsorted(r2s, dx * dx + dy * dy, side="right"),
                     np.searchsorted(rg, np.minimum(d, TWO_PI - d), side="right"))
    level = np.partition(lam, k - 1)[k - 1]
    return level, int((lam <= level).sum()), lam


def scipy_search(s, g, k=K, seed=0, chunk=50_000):
    """The general cKDTree way: 3D tree on (x, y, g * RS/RG), periodic in the scaled g."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(seed)
    scale = RS / RG
    gw = wrap_angle(g).astype(np.float64)
    pts = np.column_stack([s.astype(np.float64), (gw + np.pi) * scale])
    span = pts[:, :2].max(0) - pts[:, :2].min(0)
    lo = pts[:, :2].min(0)
    pts[:, :2] -= lo  # boxsize needs coordinates in [0, L); a box 3x the extent never wraps x, y
    tree = cKDTree(pts, boxsize=[3 * span[0] + 1, 3 * span[1] + 1, 2 * np.pi * scale])
    n = len(pts)
    out = np.empty((n, k), np.int64)
    level = np.zeros(n, np.int64)
    pending = np.arange(n)
    lev = 0
    while pending.size:
        r2s, rgl = radius_tables(RS, RG, GROWTH, [lev])
        r = RS * GROWTH**lev
        still = []
        for c0 in range(0, pending.size, chunk):
            qi = pending[c0:c0 + chunk]
            lists = tree.query_ball_point(pts[qi], r * 1.0001, p=np.inf, return_sorted=False)
            lens = np.fromiter((len(x) for x in lists), np.int64, len(lists))
            cand = np.concatenate(lists).astype(np.int64)
            qrep = np.repeat(qi, lens)
            dx = s[cand, 0] - s[qrep, 0]
            dy = s[cand, 1] - s[qrep, 1]
            d = np.abs(wrap_angle(g[cand]) - wrap_angle(g[qrep]))
            mem = (dx * dx + dy * dy < r2s[0]) & (np.minimum(d, TWO_PI - d) < rgl[0])
            qrep, cand = qrep[mem], cand[mem]
            cnt = np.bincount(np.searchsorted(qi, qrep), minlength=len(qi))
            ok = cnt >= k
            # k smallest random keys per query = uniform sample without replacement.
            order = np.lexsort((rng.random(len(cand)), qrep))
            starts = np.concatenate([[0], np.cumsum(cnt)[:-1]])
            take = (starts[ok][:, None] + np.arange(k)).ravel()
            out[qi[ok]] = cand[order][take].reshape(-1, k)
            level[qi[ok]] = lev
            still.append(qi[~ok])
        pending = np.concatenate(still)
        lev += 1
    return out, level


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=1_000_000)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--check", type=int, default=300, help="queries checked against brute force")
    ap.add_argument("--skip-scipy", action="store_true")
    ap.add_argument("--build", default="auto",
                    help="comma-separated build_index paths: auto (the device when JAX's backend is "
                         "not the CPU), host, device; the first one feeds the search")
    args = ap.parse_args()
    paths = [{"auto": None, "host": False, "device": True}[b] for b in args.build.split(",")]
    on_device = paths[0]
    s, g = paper_like_data(args.n)
    n = len(s)
    print(f"N = Q = {n:,}  k={K} radius_s={RS} radius_g={RG} growth={GROWTH:.4f}  devices={jax.devices()}")

    def build(on_device):
        return jax.block_until_ready(build_index(s, g, k=K, radius_s=RS, radius_g=RG, growth=GROWTH,
                                                 max_level=0, on_device=on_device))

    def run(key):
        index = build(on_device)
        return index, jax.block_until_ready(search_all(index, key, s, g))

    t0 = time.perf_counter()
    index, nb = run(jax.random.key(0))
    first = time.perf_counter() - t0
    times, build_t = [], []
    for r in range(args.repeats):
        t0 = time.perf_counter()
        index = build(on_device)
        t1 = time.perf_counter()
        nb = jax.block_until_ready(search_all(index, jax.random.key(r + 1), s, g))
        t2 = time.perf_counter()
        build_t.append(t1 - t0)
        times.append(t2 - t1)
    steady = float(np.median(times)) + float(np.median(build_t))
    print(f"jax grid hash: first call (compile + run) {first:.2f} s; steady state {steady:.3f} s "
          f"= build_index {np.median(build_t):.3f} s + search_all {np.median(times):.3f} s "
          f"(median of {args.repeats}; all: {', '.join(f'{t:.3f}' for t in times)})")
    print(f"  build_index, all: {', '.join(f'{t:.3f}' for t in build_t)}")
    print(f"  compile (first - steady): {first - steady:.2f} s")
    for other in paths[1:]:
        t0 = time.perf_counter()
        alt = build(other)
        alt_first = time.perf_counter() - t0
        alt_t = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            alt = build(other)
            alt_t.append(time.perf_counter() - t0)
        same = all(np.array_equal(np.asarray(a), np.asarray(b)) for a, b in
                   zip(jax.tree.leaves(index), jax.tree.leaves(alt))) and index.max_window == alt.max_window
        print(f"  build_index(on_device={other}): {np.median(alt_t):.3f} s (median of {args.repeats}; "
              f"first call {alt_first:.2f} s); the same index as on_device={on_device}: {same}")
    level = np.asarray(nb.level)
    count = np.asarray(nb.count)
    print(f"  levels: {np.bincount(level).tolist()}  base |B| mean {count[level == 0].mean():.1f}")

    rng = np.random.default_rng(1)
    grow = np.flatnonzero(level > 0)
    check = np.concatenate([rng.choice(n, min(args.check, n), replace=False),
                            rng.choice(grow, min(len(grow), args.check // 3), replace=False)])
    idx = np.asarray(nb.idx)
    bad = 0
    for q in check:
        lv, cnt, lam = brute_level(s, g, s[q], g[q])
        row = idx[q]
        bad += int(lv != level[q] or cnt != count[q] or len(set(row.tolist())) != K or (lam[row] > lv).any())
    print(f"  brute-force check on {len(check)} queries ({min(len(grow), args.check // 3)} with growth): "
          f"{'all agree' if bad == 0 else f'{bad} DISAGREE'} (level, |B|, membership, distinctness)")

    if not args.skip_scipy:
        t0 = time.perf_counter()
        _s_idx, s_level = scipy_search(s, g)
        t_scipy = time.perf_counter() - t0
        agree = float((s_level == level).mean())
        print(f"scipy cKDTree (general: periodic 3D tree, box query, exact filter, growth, sampling): "
              f"{t_scipy:.2f} s; level agreement with JAX {agree:.6f}; speed-up {t_scipy / steady:.1f}x")


if __name__ == "__main__":
    main()
