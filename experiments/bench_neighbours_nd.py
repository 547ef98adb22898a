"""Benchmark: general neighbour search (`lazyq_jax.neighbours_nd`) vs scipy cKDTree, same run.

Cases: d_s = 2, 3, 4, 6 with an angle goal and d_s = 3 with a 3-D vector goal; N = Q
(every data point is a query, as training needs); k = 20, radius_s = 0.06,
radius_g = 0.1, growth = 2**(1/3).

Data scaling. States are uniform in ``[-A, A]^d_s`` and goals uniform (angle in
``[-pi, pi)``; vector in ``[-B, B]^3`` with ``B`` such that a goal ball of radius
``radius_g`` holds 1/(10 pi) of the goals, as the angle's ``2 radius_g / 2 pi`` does).
``A`` is chosen so that an interior query expects ``TARGET = 60`` points in its base
neighbourhood::

    N * V_d(radius_s) / (2A)^d_s * p_goal = TARGET,   V_d(r) = pi^(d/2) r^d / Gamma(d/2 + 1)

Queries near the faces of the box see fewer points (at d_s = 6 the box is only ~4
radii wide, so most queries are "near a face"), hence the measured mean base
count printed below is lower and some queries grow.

cKDTree "the general way": one tree over all dimensions in radius units (state /
radius_s; the angle / radius_g in a periodic box of period 2 pi / radius_g; a vector
goal / radius_g), ``query_ball_point`` with the box (p = inf) of half-width
``growth**L`` (slightly widened), which contains the product of the two balls;
exact filtering of the candidates with the float32 formula; queries short of k
grow to the next level; then k members sampled without replacement (k smallest
random keys). Timed on the same data in the same run.

    flock /tmp/lazyq_bench.lock .venv/bin/python experiments/bench_neighbours_nd.py [--n 1000000]
"""

from __future__ import annotations

import argparse
import math
import time

import jax
import numpy as np

from lazyq_jax.neighbours import radius_tables, wrap_angle
from lazyq_jax.neighbours.common import TWO_PI
from lazyq_jax.neighbours.nd import build_index_nd, search_all_nd

K, RS, RG, GROWTH = 20, 0.06, 0.1, 2 ** (1 / 3)
TARGET = 60.0
CASES = [(2, "angle"), (3, "angle"), (4, "angle"), (6, "angle"), (3, "vector")]


def ball_volume(d, r):
    return math.pi ** (d / 2) * r**d / math.gamma(d / 2 + 1)


def make_data(n, d_s, goal, seed=0):
    rng = np.random.default_rng(seed)
    p_goal = 2 * RG / (2 * math.pi)
    if goal == "angle":
        g = rng.uniform(-np.pi, np.pi, n).astype(np.float32)
    else:
        b = 0.5 * (ball_volume(3, RG) / p_goal) ** (1 / 3)
        g = rng.uniform(-b, b, (n, 3)).astype(np.float32)
    a = 0.5 * (n * ball_volume(d_s, RS) * p_goal / TARGET) ** (1 / d_s)
    s = rng.uniform(-a, a, (n, d_s)).astype(np.float32)
    return s, g, a


def float32_levels(s, g, qs, qg, cand_q, cand, goal, levels):
    """Entry level (smallest L in ``levels`` with membership, else len) of candidate pairs."""
    with np.errstate(over="ignore"):  # radii beyond float32 at high levels: inf
        r2s, rg = radius_tables(RS, RG, GROWTH, levels)
        rg2, _ = radius_tables(RG, RG, GROWTH, levels)
    ds2 = np.zeros(len(cand), np.float32)
    for c in range(s.shape[1]):
        v = s[cand, c] - qs[cand_q, c]
        ds2 = ds2 + v * v
    lam = np.searchsorted(r2s, ds2, side="right")
    if goal == "angle":
        d = np.abs(wrap_angle(g[cand]) - wrap_angle(qg[cand_q]))
        lam = np.maximum(lam, np.searchsorted(rg, np.minimum(d, TWO_PI - d), side="right"))
    else:
        dg2 = np.zeros(len(cand), np.float32)
        for c in range(g.shape[1]):
            v = g[cand, c] - qg[cand_q, c]
            dg2 = dg2 + v * v
        lam = np.maximum(lam, np.searchsorted(rg2, dg2, side="right"))
    return lam


def scipy_search(s, g, goal, k=K, seed=0, chunk=20_000):
    """The general cKDTree way (module docstring). Returns ``(idx, level, count)``."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(seed)
    n = len(s)
    us = s.astype(np.float64) / RS
    if goal == "angle":
        ug = (wrap_angle(g).astype(np.float64) + np.pi)[:, None] / RG
        period_g = [2 * np.pi / RG]
    else:
        ug = g.astype(np.float64) / RG
        period_g = None
    pts = np.concatenate([us, ug], axis=1)
    lo = pts.min(0)
    span = pts.max(0) - lo
    pts_t = pts - lo
    box = 3 * span + 10  # non-periodic dims: a box 3x the extent never wraps
    if period_g is not None:
        box[-1] = period_g[0]
        pts_t[:, -1] = np.mod(pts_t[:, -1] + lo[-1], period_g[0])
    tree = cKDTree(pts_t, boxsize=box)
    out = np.empty((n, k), np.int64)
    level = np.zeros(n, np.int64)
    count = np.zeros(n, np.int64)
    pending = np.arange(n)
    lev = 0
    while pending.size:
        r = GROWTH**lev * (1 + 1e-4)
        still = []
        for c0 in range(0, pending.size, chunk):
            qi = pending[c0:c0 + chunk]
            lists = tree.query_ball_point(pts_t[qi], r, p=np.inf, return_sorted=False)
            lens = np.fromiter((len(x) for x in lists), np.int64, len(lists))
            cand = np.concatenate(lists).astype(np.int64)
            qrep = np.repeat(qi, lens)
            mem = float32_levels(s, g, s, g, qrep, cand, goal, [lev]) == 0
            qrep, cand = qrep[mem], cand[mem]
            cnt = np.bincount(np.searchsorted(qi, qrep), minlength=len(qi))
            ok = cnt >= k
            order = np.lexsort((rng.random(len(cand)), qrep))  # k smallest keys: uniform sample
            starts = np.concatenate([[0], np.cumsum(cnt)[:-1]])
            take = (starts[ok][:, None] + np.arange(k)).ravel()
            out[qi[ok]] = cand[order][take].reshape(-1, k)
            level[qi[ok]] = lev
            count[qi[ok]] = cnt[ok]
            still.append(qi[~ok])
        pending = np.concatenate(still)
        lev += 1
    return out, level, count


def brute_check(s, g, goal, nb, queries):
    """(level, |B|, membership, distinctness) of the JAX result against the float32 formula."""
    level, count, idx = (np.asarray(a) for a in (nb.level, nb.count, nb.idx))
    n = len(s)
    bad = 0
    for q in queries:
        lam = float32_levels(s, g, s, g, np.full(n, q), np.arange(n), goal, np.arange(400))
        lv = np.partition(lam, K - 1)[K - 1]
        row = idx[q]
        bad += int(lv != level[q] or (lam <= lv).sum() != count[q] or len(set(row.tolist())) != K
                   or (lam[row] > lv).any())
    return bad


def run_case(n, d_s, goal, repeats, check, skip_scipy):
    s, g, a = make_data(n, d_s, goal)
    print(f"\n== d_s={d_s} goal={goal}: N = Q = {n:,}, states in [-{a:.3f}, {a:.3f}]^{d_s} "
          f"({2 * a / RS:.1f} radii per axis)")

    def once(r):
        t0 = time.perf_counter()
        index = build_index_nd(s, g, k=K, radius_s=RS, radius_g=RG, growth=GROWTH)
        t1 = time.perf_counter()
        stats = {}
        nb = jax.block_until_ready(search_all_nd(index, jax.random.key(r), s, g, stats=stats))
        return nb, stats, t1 - t0, time.perf_counter() - t1

    t0 = time.perf_counter()
    nb, stats, _, _ = once(0)
    first = time.perf_counter() - t0
    builds, searches = [], []
    for r in range(repeats):
        nb, stats, tb, ts = once(r + 1)
        builds.append(tb)
        searches.append(ts)
    steady = float(np.median(builds) + np.median(searches))
    level, count = np.asarray(nb.level), np.asarray(nb.count)
    grid = [(ax.col, ax.n, round(ax.width / ax.radius, 3), ax.rep) for ax in stats["grid"]]
    print(f"jax: first call {first:.2f} s; steady {steady:.3f} s = build {np.median(builds):.3f} + "
          f"search {np.median(searches):.3f} (median of {repeats})")
    print(f"  grid (col, cells, width/radius, replication): {grid or 'full scan'}")
    passes = []
    for p in stats["passes"]:
        extra = (" full" if p["full"] else "") + (f" reruns={p['reruns']}" if p["reruns"] else "")
        passes.append(f"L{p['lo']}-{p['hi']} q={p['queries']} items/q={p['items']:.0f}{extra} "
                      f"{p['seconds']:.2f}s")
    print("  passes: " + "; ".join(passes))
    print(f"  levels: {np.bincount(level).tolist()}  base |B| mean {count[level == 0].mean():.1f}")
    rng = np.random.default_rng(1)
    grow = np.flatnonzero(level > 0)
    sample = np.concatenate([rng.choice(n, min(check, n), replace=False),
                             rng.choice(grow, min(len(grow), check // 3), replace=False)])
    bad = brute_check(s, g, goal, nb, sample)
    print(f"  brute-force check on {len(sample)} queries: {'all agree' if bad == 0 else f'{bad} DISAGREE'}")
    if skip_scipy:
        return d_s, goal, steady, None
    t0 = time.perf_counter()
    _, s_level, s_count = scipy_search(s, g, goal)
    t_scipy = time.perf_counter() - t0
    print(f"scipy cKDTree (general): {t_scipy:.2f} s; speed-up {t_scipy / steady:.1f}x; "
          f"agreement with jax: level {np.mean(s_level == level):.6f}, count {np.mean(s_count == count):.6f}")
    return d_s, goal, steady, t_scipy


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=1_000_000)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--check", type=int, default=60, help="queries checked against brute force")
    ap.add_argument("--cases", default=",".join(f"{d}{g[0]}" for d, g in CASES),
                    help="e.g. 2a,3a,4a,6a,3v")
    ap.add_argument("--skip-scipy", action="store_true")
    args = ap.parse_args()
    print(f"k={K} radius_s={RS} radius_g={RG} growth={GROWTH:.4f} devices={jax.devices()}")
    rows = []
    for case in args.cases.split(","):
        d_s, goal = int(case[:-1]), {"a": "angle", "v": "vector"}[case[-1]]
        rows.append(run_case(args.n, d_s, goal, args.repeats, args.check, args.skip_scipy))
    print(f"\nsummary, N = Q = {args.n:,} (steady state incl. build; cKDTree the general way):")
    for d_s, goal, steady, t_scipy in rows:
        vs = f"cKDTree {t_scipy:8.2f} s  speed-up {t_scipy / steady:6.1f}x" if t_scipy else ""
        print(f"  d_s={d_s} {goal:6s}  jax {steady:7.3f} s  {vs}")


if __name__ == "__main__":
    main()
