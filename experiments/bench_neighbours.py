"""Neighbour-search benchmarks (paper §V-A-2): every engine of :mod:`lazyq_jax.neighbours`
against a yardstick timed in the same run, or old against new (``--old``).

Cases (``--cases``, comma-separated):

* ``paper``: the grid (``build_index`` + ``search_all``) on data like the paper's: ``N/100``
  finger states uniform in ``[-1, 1]^2`` outside a disk of radius 0.31, each paired with 100
  goals uniform in ``[-pi, pi)``;
* ``2a``, ``3a``, ``4a``, ``6a`` (``d_s`` with an angle goal), ``3v`` (a 3-D vector goal),
  ``2n`` (no goal): the general search (``build_index_nd`` + ``search_all_nd``), states
  uniform in ``[-A, A]^d_s`` with ``N V_d(radius_s) / (2A)^d_s p_goal = 60`` (an interior
  query expects 60 points in its base neighbourhood; ``p_goal = 2 radius_g / 2 pi``, the
  angle's, also for a vector goal uniform in ``[-B, B]^3``; 1 without a goal), so that
  queries near the faces grow (at d_s = 6 most of them);
* ``q3``, ``q5``: the policy's per-step query (``build_policy_index`` + a jitted
  ``query_policy`` of ``--batch`` queries) on data like the arm task's: ``N/100`` states
  uniform in a box of half-widths (pi/2, 2.5, 2.5, [0.5, 0.5]), each with 100 random angle
  goals, radius_s 0.12, max_level 5; queries uniform in the box with random goals.

A search is every data point's (N = Q, as training needs; k = 20, radius_s = 0.06, radius_g
= 0.1, growth = 2^(1/3)): it prints its first call (compile + run), its steady state (build
+ search, medians of ``--repeats``), the levels, a brute-force check of sample queries
against the float32 formula (level, |B|, membership, distinctness), then scipy's cKDTree
the general way: one tree over all dimensions in radius units (the angle periodic), box
queries of half-width ``growth**L``, the exact float32 filter, growth, k smallest random
keys.  A policy case prints ms a query against the scan of all data
(``query_neighbours_scan`` on ``--scan-queries`` of the batch; levels and counts must agree).

``--old CHECKOUT``: the package of an earlier checkout (copied as ``lazyq_old``) against
this one instead, alternately in one process (a shared machine's speed drifts 15-30 %
between processes), their results for one key compared element by element.

    flock /tmp/lazyq_bench.lock .venv/bin/python experiments/bench_neighbours.py [--n 1000000]
    .venv/bin/python experiments/bench_neighbours.py --cases 2a,3a,4a,6a,3v --repeats 3
    .venv/bin/python experiments/bench_neighbours.py --cases q3,q5
    git worktree add /tmp/old <rev>
    .venv/bin/python experiments/bench_neighbours.py --old /tmp/old --cases paper,3a,q3 --repeats 6
    .venv/bin/python experiments/bench_neighbours.py --old /tmp/old --data runs/pm/data/0/dataset.npz \\
        --radius-s 0.5 --radius-g 1.0                                    # pointmaze's dataset
"""

from __future__ import annotations

import argparse
import importlib
import math
import pathlib
import shutil
import sys
import tempfile
import time

import jax
import numpy as np
from _common import alternating, timed

import lazyq_jax.neighbours as new_package
from lazyq_jax.neighbours import radius_tables, wrap_angle
from lazyq_jax.neighbours.common import TWO_PI

K, RS, RG, GROWTH = 20, 0.06, 0.1, 2 ** (1 / 3)
POLICY = {"k": 20, "radius_s": 0.12, "radius_g": 0.1, "growth": GROWTH, "max_level": 5}
HALF_WIDTHS = (np.pi / 2, 2.5, 2.5, 0.5, 0.5)


def ball_volume(d, r):
    return math.pi ** (d / 2) * r**d / math.gamma(d / 2 + 1)


def make_data(case: str, n: int, seed: int = 0):
    """``(s, g)`` of a case (module docstring)."""
    rng = np.random.default_rng(seed)
    if case == "paper":
        states = np.empty((0, 2))
        while len(states) < max(n // 100, 1):
            p = rng.uniform(-1, 1, (2 * max(n // 100, 1), 2))
            states = np.concatenate([states, p[np.linalg.norm(p, axis=1) > 0.31]])
        s = np.repeat(states[:max(n // 100, 1)], 100, axis=0)[:n].astype(np.float32)
        return s, rng.uniform(-np.pi, np.pi, len(s)).astype(np.float32)
    if case.startswith("q"):
        hw = np.asarray(HALF_WIDTHS[:int(case[1:])], np.float32)
        s = np.repeat(rng.uniform(-hw, hw, (max(n // 100, 1), hw.size)).astype(np.float32), 100, axis=0)
        return s, rng.uniform(-np.pi, np.pi, s.shape[0]).astype(np.float32)
    d_s, p_goal = int(case[:-1]), 2 * RG / (2 * math.pi)
    if case[-1] not in "anv" or not case[:-1].isdigit():
        raise SystemExit(f"unknown case {case!r} (paper, q3, q5, or d_s and a, v or n: 2a, 3v, 2n, ...)")
    if case[-1] == "a":
        g = rng.uniform(-np.pi, np.pi, n).astype(np.float32)
    elif case[-1] == "n":
        g = None
    else:
        b = 0.5 * (ball_volume(3, RG) / p_goal) ** (1 / 3)
        g = rng.uniform(-b, b, (n, 3)).astype(np.float32)
    a = 0.5 * (n * ball_volume(d_s, RS) * (1.0 if g is None else p_goal) / 60.0) ** (1 / d_s)
    return rng.uniform(-a, a, (n, d_s)).astype(np.float32), g


def float32_levels(s, g, cand_q, cand, levels):
    """Entry level (smallest L in ``levels`` with membership, else len) of the pairs
    (query ``cand_q``, point ``cand``), every query a data point; the float32 formula."""
    r2s, rg = radius_tables(RS, RG, GROWTH, levels)
    rg2, _ = radius_tables(RG, RG, GROWTH, levels)
    ds2 = np.zeros(len(cand), np.float32)
    for c in range(s.shape[1]):
        ds2 = ds2 + (s[cand, c] - s[cand_q, c]) ** 2
    lam = np.searchsorted(r2s, ds2, side="right")
    if g is None:
        return lam
    if g.ndim == 1:
        d = np.abs(wrap_angle(g[cand]) - wrap_angle(g[cand_q]))
        return np.maximum(lam, np.searchsorted(rg, np.minimum(d, TWO_PI - d), side="right"))
    dg2 = np.zeros(len(cand), np.float32)
    for c in range(g.shape[1]):
        dg2 = dg2 + (g[cand, c] - g[cand_q, c]) ** 2
    return np.maximum(lam, np.searchsorted(rg2, dg2, side="right"))


def brute_check(s, g, nb, queries):
    """Queries whose (level, |B|, membership, distinctness) disagree with the float32 formula."""
    level, count, idx = (np.asarray(a) for a in (nb.level, nb.count, nb.idx))
    bad = 0
    for q in queries:
        with np.errstate(over="ignore"):  # radii beyond float32 at high levels: inf
            lam = float32_levels(s, g, np.full(len(s), q), np.arange(len(s)), np.arange(400))
        lv = np.partition(lam, K - 1)[K - 1]
        row = idx[q]
        bad += int(lv != level[q] or (lam <= lv).sum() != count[q] or len(set(row.tolist())) != K
                   or (lam[row] > lv).any())
    return bad


def scipy_search(s, g, seed=0, chunk=20_000):
    """The general cKDTree way (module docstring): ``(level, count)`` of every data point."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(seed)
    goal = np.zeros((len(s), 0)) if g is None else (wrap_angle(g) + np.pi)[:, None] if g.ndim == 1 else g
    pts = np.concatenate([s.astype(np.float64) / RS, goal.astype(np.float64) / RG], axis=1)
    pts -= pts.min(0)
    box = 3 * pts.max(0) + 10  # non-periodic dims: a box 3x the extent never wraps
    if g is not None and g.ndim == 1:
        box[-1] = 2 * np.pi / RG
        pts[:, -1] = np.mod(pts[:, -1], box[-1])
    tree = cKDTree(pts, boxsize=box)
    level, count = np.zeros(len(s), np.int64), np.zeros(len(s), np.int64)
    pending, lev = np.arange(len(s)), 0
    while pending.size:
        still = []
        for c0 in range(0, pending.size, chunk):
            qi = pending[c0:c0 + chunk]
            lists = tree.query_ball_point(pts[qi], GROWTH**lev * (1 + 1e-4), p=np.inf, return_sorted=False)
            cand = np.concatenate(lists).astype(np.int64)
            qrep = np.repeat(qi, [len(x) for x in lists])
            mem = float32_levels(s, g, qrep, cand, [lev]) == 0
            qrep, cand = qrep[mem], cand[mem]
            cnt = np.bincount(np.searchsorted(qi, qrep), minlength=len(qi))
            ok = cnt >= K
            order = np.lexsort((rng.random(len(cand)), qrep))  # k smallest keys: a uniform sample
            starts = np.concatenate([[0], np.cumsum(cnt)[:-1]])
            _idx = cand[order][(starts[ok][:, None] + np.arange(K)).ravel()].reshape(-1, K)
            level[qi[ok]], count[qi[ok]] = lev, cnt[ok]
            still.append(qi[~ok])
        pending, lev = np.concatenate(still), lev + 1
    return level, count


def policy_batch(d_s):
    """``--batch`` queries uniform in the arm-like box, with random goals."""
    rng, hw = np.random.default_rng(1), np.asarray(HALF_WIDTHS[:d_s], np.float32)
    return (rng.uniform(-hw, hw, (ARGS.batch, d_s)).astype(np.float32),
            rng.uniform(-np.pi, np.pi, ARGS.batch).astype(np.float32))


def engine(m, case, s, g, on_device=None):
    """``(build, run)`` of a case from the neighbours package ``m``: ``run(index, key)`` searches
    every data point (the engine ``find_neighbours`` picks) or answers a policy batch."""
    if case.startswith("q"):
        query, (qs, qg) = importlib.import_module(m.__name__ + ".query"), policy_batch(s.shape[1])
        fn = jax.jit(query.query_policy)
        return (lambda: query.build_policy_index(s, g, **POLICY)), (lambda index, key: fn(index, key, qs, qg))
    if m.is_grid_space(s, g):
        return (lambda: m.build_index(s, g, k=K, radius_s=RS, radius_g=RG, growth=GROWTH, max_level=0,
                                      on_device=on_device),
                lambda index, key, **kw: m.search_all(index, key, s, g))
    nd = importlib.import_module(m.__name__ + ".nd")
    return (lambda: nd.build_index_nd(s, g, k=K, radius_s=RS, radius_g=RG, growth=GROWTH),
            lambda index, key, **kw: nd.search_all_nd(index, key, s, g, **kw))


def run_search(case, s, g, on_device):
    """A search case (module docstring): ``(steady s, cKDTree s or None)``."""
    build, search = engine(new_package, case, s, g, on_device[0])
    stats, t = {}, time.perf_counter()
    nb = jax.block_until_ready(search(build(), jax.random.key(0), stats=stats))
    first, builds, searches = time.perf_counter() - t, [], []
    for r in range(ARGS.repeats):
        t0 = time.perf_counter()
        index = jax.block_until_ready(build())
        t1 = time.perf_counter()
        jax.block_until_ready(search(index, jax.random.key(r + 1)))
        builds.append(t1 - t0)
        searches.append(time.perf_counter() - t1)
    steady = float(np.median(builds) + np.median(searches))
    print(f"jax: first call {first:.2f} s; steady {steady:.3f} s = build {np.median(builds):.3f} + search "
          f"{np.median(searches):.3f} (median of {ARGS.repeats}; searches {', '.join(f'{x:.3f}' for x in searches)})")
    if stats:
        print(f"  grid (col, cells, width/radius, replication): "
              f"{[(ax.col, ax.n, round(ax.width / ax.radius, 3), ax.rep) for ax in stats['grid']] or 'full scan'}")
        print("  passes: " + "; ".join(f"L{p['lo']}-{p['hi']} q={p['queries']} items/q={p['items']:.0f}"
                                       + (" full" if p["full"] else "") + f" {p['seconds']:.2f}s"
                                       for p in stats["passes"]))
    for other in on_device[1:] if new_package.is_grid_space(s, g) else []:  # the grid's other build
        alt, first_alt, med = timed(engine(new_package, case, s, g, other)[0], repeats=ARGS.repeats)
        same = all(np.array_equal(a, b) for a, b in zip(jax.tree.leaves(index), jax.tree.leaves(alt)))
        print(f"  build_index(on_device={other}): {med:.3f} s (median of {ARGS.repeats}; first call "
              f"{first_alt:.2f} s); the same index as on_device={on_device[0]}: {same}")
    level, count = np.asarray(nb.level), np.asarray(nb.count)
    print(f"  levels: {np.bincount(level).tolist()}  base |B| mean {count[level == 0].mean():.1f}")
    rng, grow = np.random.default_rng(1), np.flatnonzero(level > 0)
    check = ARGS.check if ARGS.check is not None else 300 if case == "paper" else 60
    sample = np.concatenate([rng.choice(len(s), min(check, len(s)), replace=False),
                             rng.choice(grow, min(len(grow), check // 3), replace=False)])
    bad = brute_check(s, g, nb, sample)
    print(f"  brute-force check on {len(sample)} queries: {'all agree' if bad == 0 else f'{bad} DISAGREE'}")
    if ARGS.skip_baseline:
        return steady, None
    t = time.perf_counter()
    s_level, s_count = scipy_search(s, g)
    t_scipy = time.perf_counter() - t
    print(f"scipy cKDTree (general): {t_scipy:.2f} s; speed-up {t_scipy / steady:.1f}x; agreement with jax: "
          f"level {np.mean(s_level == level):.6f}, count {np.mean(s_count == count):.6f}")
    return steady, t_scipy


def run_policy(case, s, g):
    """A policy case (module docstring): ``(ms a query, the scan's ms a query or None)``."""
    build, query = engine(new_package, case, s, g)
    t = time.perf_counter()
    index = build()
    build_s, key = time.perf_counter() - t, jax.random.key(0)
    nb, first, med = timed(query, index, key, repeats=ARGS.repeats)
    ms, level = 1e3 * med / ARGS.batch, np.asarray(nb.level)
    print(f"policy index: {ms:.3f} ms a query (batch {ARGS.batch}, median of {ARGS.repeats}); build {build_s:.2f} s, "
          f"first call {first:.1f} s; overflow {int(np.sum(nb.overflow))}; levels -1..{POLICY['max_level']}: "
          f"{np.bincount(level + 1, minlength=POLICY['max_level'] + 2).tolist()}; phases lo-hi:slots x items "
          + "+".join(f"{p.lo}-{p.hi}:{p.slots(ARGS.batch)}x{p.cap}" for p in index.phases))
    if ARGS.skip_baseline:
        return ms, None
    m, (qs, qg) = ARGS.scan_queries, policy_batch(s.shape[1])
    scan = new_package.build_scan_index(s, g, **POLICY)
    old, _, med_scan = timed(jax.jit(new_package.query_neighbours_scan), scan, key, qs[:m], qg[:m],
                             repeats=ARGS.repeats)
    for a, b in ((old.level, nb.level[:m]), (old.count, nb.count[:m])):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    print(f"scan of all data: {1e3 * med_scan / m:.2f} ms a query ({m} queries; the same levels and counts); "
          f"the policy index {1e3 * med_scan / m / ms:.0f}x faster")
    return ms, 1e3 * med_scan / m


def import_old(checkout: str, into: str):
    """The neighbours package of ``checkout`` as ``lazyq_old.neighbours`` (its imports renamed)."""
    src = pathlib.Path(checkout) / "lazyq_jax"
    if not (src / "neighbours").is_dir():
        raise SystemExit(f"--old {checkout}: no lazyq_jax/neighbours there (give a checkout of this repository)")
    shutil.copytree(src, pathlib.Path(into) / "lazyq_old")
    for f in (pathlib.Path(into) / "lazyq_old").rglob("*.py"):
        f.write_text(f.read_text().replace("lazyq_jax", "lazyq_old"))
    sys.path.insert(0, into)
    return importlib.import_module("lazyq_old.neighbours")


def run_old_against_new(old_package, case, s, g):
    """Old and new in turn: build (searches) or the jitted batch (policy), medians and the
    paired ratio new / old; both results for key 0 compared element by element."""
    versions = {"old": engine(old_package, case, s, g), "new": engine(new_package, case, s, g)}
    indices = {v: jax.block_until_ready(build()) for v, (build, _) in versions.items()}
    results = [jax.block_until_ready(run(indices[v], jax.random.key(0))) for v, (_, run) in versions.items()]
    same = all(np.array_equal(np.asarray(getattr(results[0], f)), np.asarray(getattr(results[1], f)))
               for f in ("idx", "level", "count"))
    print(f"old and new results (key 0): {'identical' if same else 'DIFFER'}")
    fns = {}
    for v, (build, run) in versions.items():
        if not case.startswith("q"):
            fns[f"{v} build"] = build
        fns[f"{v} {'query' if case.startswith('q') else 'search'}"] = (
            lambda run=run, index=indices[v]: run(index, jax.random.key(1)))
    times = alternating(fns, ARGS.repeats)
    for name, v in times.items():
        print(f"  {name:12s} median {np.median(v):.4g} s   " + " ".join(f"{x:.4g}" for x in v))
    for what in sorted({name.split()[1] for name in times}):
        new, old = np.array(times[f"new {what}"]), np.array(times[f"old {what}"])
        print(f"  {what}: new / old median {np.median(new) / np.median(old):.3f}, paired ratio median "
              f"{np.median(new / old):.3f}, new faster in {int((new < old).sum())} of {len(new)}")


def main():
    global ARGS, K, RS, RG
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", default="paper", help="comma-separated: paper, 2a, 3a, 4a, 6a, 3v, 2n, q3, q5")
    ap.add_argument("--n", type=int, default=1_000_000, help="data points (a policy case: N/100 states x 100)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--check", type=int, help="queries checked by brute force (default 300 paper, 60 other)")
    ap.add_argument("--skip-baseline", "--skip-scipy", action="store_true", help="no cKDTree, no scan")
    ap.add_argument("--build", default="auto", help="paper: comma-separated build_index paths, the first "
                    "searched: auto (the device when JAX's backend is not the CPU), host, device")
    ap.add_argument("--batch", type=int, default=320, help="policy cases: queries a batch")
    ap.add_argument("--scan-queries", type=int, default=32, help="policy cases: queries the scan answers")
    ap.add_argument("--old", help="a checkout of an earlier version: old against new")
    ap.add_argument("--data", help="a dataset .npz (arrays s [N, d_s], g optional) instead of --cases")
    ap.add_argument("--k", type=int, default=K)
    ap.add_argument("--radius-s", type=float, default=RS)
    ap.add_argument("--radius-g", type=float, default=RG)
    ARGS = ap.parse_args()
    K, RS, RG = ARGS.k, ARGS.radius_s, ARGS.radius_g
    on_device = [{"auto": None, "host": False, "device": True}[b] for b in ARGS.build.split(",")]
    print(f"k={K} radius_s={RS} radius_g={RG} growth={GROWTH:.4f} devices={jax.devices()}")
    with tempfile.TemporaryDirectory() as tmp:
        old = import_old(ARGS.old, tmp) if ARGS.old else None
        rows = []
        for case in [ARGS.data] if ARGS.data else ARGS.cases.split(","):
            if ARGS.data:
                with np.load(case) as f:
                    s, g = f["s"].astype(np.float32), f["g"].astype(np.float32) if "g" in f.files else None
            else:
                s, g = make_data(case, ARGS.n)
            print(f"\n== {case}: N = {len(s):,}, d_s = {s.shape[1]}, goal "
                  f"{'none' if g is None else 'angle' if g.ndim == 1 else f'vector of {g.shape[1]}'}")
            if old is not None:
                run_old_against_new(old, case, s, g)
            else:
                rows.append((case, *(run_policy if case.startswith("q") else run_search)(
                    *(case, s, g) + (() if case.startswith("q") else (on_device,)))))
    for case, jax_s, base in rows:  # the summary
        unit = ("ms a query", "scan") if case.startswith("q") else ("s steady", "cKDTree")
        print(f"  {case:6s} jax {jax_s:8.3f} {unit[0]}" + (f"  {unit[1]} {base:8.2f}  ratio {base / jax_s:6.1f}x"
                                                            if base else ""))


if __name__ == "__main__":
    main()
