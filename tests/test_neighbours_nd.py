"""General neighbour search (neighbours_nd) against a brute-force NumPy reference.

The reference below is written independently of the module: the float32 formula of
the module docstring, evaluated with NumPy (which never fuses a multiply into an add).
"""

import math

import jax
import numpy as np
import pytest

from lazyq_jax.neighbours.common import TWO_PI, radius_tables, wrap_angle
from lazyq_jax.neighbours.nd import (
    _pack,
    build_index_nd,
    find_neighbours_nd,
    membership_level_reference,
    search_all_nd,
)

RS, RG, G = 0.06, 0.1, 2 ** (1 / 3)


def brute_lam(s, g, qs, qg, rs=RS, rg=RG, growth=G, levels=300):
    """Entry level ``[Q, N]`` of every (query, point): smallest L with the point in B_L."""
    s, qs = np.asarray(s, np.float32), np.asarray(qs, np.float32)
    lv = np.arange(levels)
    with np.errstate(over="ignore"):
        r2s, rgl = radius_tables(rs, rg, growth, lv)
        rg2 = ((rg * growth ** lv.astype(np.float64)) ** 2).astype(np.float32)
    ds2 = np.zeros((len(qs), len(s)), np.float32)
    for c in range(s.shape[1]):  # left to right, every op rounded to float32
        v = s[None, :, c] - qs[:, None, c]
        ds2 = ds2 + v * v
    lam = np.searchsorted(r2s, ds2.ravel(), side="right").reshape(ds2.shape)
    if g is None:
        return lam
    g, qg = np.asarray(g, np.float32), np.asarray(qg, np.float32)
    if g.ndim == 1:
        d = np.abs(wrap_angle(g)[None, :] - wrap_angle(qg)[:, None])
        dg, table = np.minimum(d, TWO_PI - d), rgl
    else:
        dg = np.zeros((len(qs), len(s)), np.float32)
        for c in range(g.shape[1]):
            v = g[None, :, c] - qg[:, None, c]
            dg = dg + v * v
        table = rg2
    return np.maximum(lam, np.searchsorted(table, dg.ravel(), side="right").reshape(dg.shape))


def assert_exact(nb, lam, k):
    """Level (minimal), count, membership and distinctness of every row."""
    idx, level, count = (np.asarray(a) for a in (nb.idx, nb.level, nb.count))
    q = lam.shape[0]
    assert idx.shape == (q, k) and level.shape == (q,) and count.shape == (q,)
    ref_level = np.partition(lam, k - 1, axis=1)[:, k - 1]
    np.testing.assert_array_equal(level, ref_level)
    np.testing.assert_array_equal(count, (lam <= level[:, None]).sum(1))
    below = (lam <= (level - 1)[:, None]).sum(1)
    assert ((level == 0) | (below < k)).all(), "level not minimal"
    assert (np.take_along_axis(lam, idx, 1) <= level[:, None]).all(), "sampled a non-member"
    assert all(len(set(row)) == k for row in idx.tolist()), "indices not distinct"
    return level


def make_case(d_s, goal, n, q, spread, seed, far=False):
    """Data uniform in a box of ``spread`` state radii a side (angle goals crowd +-pi, so
    neighbourhoods depend on the wrap-around); queries: data points and, for a fifth of them,
    data points moved by about half a radius or (``far``) points anywhere, with any angle (growth
    up to ~15 levels)."""
    rng = np.random.default_rng(seed)
    s = rng.uniform(-0.5, 0.5, (n, d_s)).astype(np.float32) * np.float32(spread * RS)
    if goal == "angle":
        g = (np.pi - rng.uniform(-0.7, 0.7, n)).astype(np.float32)
    elif goal is None:
        g = None
    else:
        g = rng.uniform(-0.5, 0.5, (n, goal)).astype(np.float32) * np.float32(4 * RG)
    pick = rng.integers(0, n, q)
    qs, qg = s[pick].copy(), None if g is None else g[pick].copy()
    moved = np.arange(q - q // 5, q)
    if far:
        qs[moved] = rng.uniform(-0.6, 0.6, (len(moved), d_s)) * (spread * RS)
    else:
        qs[moved] += rng.normal(0, RS / 4, (len(moved), d_s)).astype(np.float32)
    if g is not None and g.ndim == 1:
        qg[moved] = rng.uniform(-4, 4, len(moved)) if far else qg[moved] + rng.normal(0, RG / 4, len(moved))
    elif g is not None:
        qg[moved] += rng.normal(0, 2 * RG if far else RG / 4, (len(moved), goal)).astype(np.float32)
    return s, g, qs, qg


# (d_s, goal, n, q, spread, k, grid): goal "angle", None or d_g; grid None = chosen by cost.
CASES = {
    "ds1-angle": (1, "angle", 1500, 200, 18, 20, None),
    "ds3-angle-sparse-far": (3, "angle", 1500, 200, 12, 20, None),
    "ds6-angle": (6, "angle", 1500, 150, 1.9, 20, None),
    "ds3-vec2": (3, 2, 1500, 150, 5, 20, None),
    "ds1-vec3-k60": (1, 3, 1500, 150, 5, 60, None),
    "ds3-none-k40": (3, None, 1200, 150, 5, 40, None),
    "ds6-none": (6, None, 1200, 150, 2.2, 20, None),
    # Forced layouts: the angle replicated 4x as first axis (sparse: later passes scan all
    # blocks); a state axis replicated 3x, then two goal axes (the chord in the goal block);
    # no grid at all.
    "ds3-angle-sparse-far-grid-rep4": (3, "angle", 1500, 150, 12, 20, ((3, 0.5, 4), (0, 0.5), (1, 0.5))),
    "ds3-vec2-grid-rep3-goal-chord": (3, 2, 1500, 150, 4.5, 20, ((0, 1.0, 3), (3, 0.5), (4, 0.5))),
    "ds3-angle-far-full-scan": (3, "angle", 1200, 100, 8, 20, ()),
}


@pytest.fixture(scope="module", params=sorted(CASES))
def case(request):
    d_s, goal, n, q, spread, k, grid = CASES[request.param]
    s, g, qs, qg = make_case(d_s, goal, n, q, spread, seed=len(request.param), far="far" in request.param)
    stats = {}
    nb = find_neighbours_nd(jax.random.key(7), s, g, qs, qg, k=k, grid=grid, stats=stats)
    return request.param, (s, g, qs, qg, k, grid), nb, stats


def test_matches_brute_force(case):
    name, (s, g, qs, qg, k, grid), nb, stats = case
    lam = brute_lam(s, g, qs, qg)
    level = assert_exact(nb, lam, k)
    base = (lam == 0).sum(1)
    if name.endswith(("k60", "k40")):
        assert (base < k).mean() > 0.5, "k should exceed most base neighbourhoods"
    if "sparse" in name:
        assert level.max() > 3 and (level > 3).mean() > 0.2, f"want levels > 3, got {np.bincount(level)}"
    if grid == ():
        assert stats["grid"] == () and all(p["full"] for p in stats["passes"])
    elif grid is not None:
        want = [(a[0], a[2] if len(a) == 3 else 1) for a in grid]
        assert [(ax.col, ax.rep) for ax in stats["grid"]] == want
    if "rep4" in name:
        assert any(p["full"] for p in stats["passes"]) and not stats["passes"][0]["full"]


def test_reference_helper_agrees_with_test_reference(case):
    _, (s, g, qs, qg, _, _), _, _ = case
    qg = None if qg is None else qg[:40]
    np.testing.assert_array_equal(membership_level_reference(s, g, qs[:40], qg, max_level=299),
                                  brute_lam(s, g, qs[:40], qg))


def test_wrap_around_pi():
    s = np.zeros((4, 3), np.float32)
    g = np.array([np.pi - 0.02, -np.pi + 0.03, 0.0, np.pi], np.float32)
    nb = find_neighbours_nd(jax.random.key(1), s, g, s[:1], np.array([-np.pi + 0.01], np.float32), k=3)
    assert int(nb.level[0]) == 0 and int(nb.count[0]) == 3
    assert set(np.asarray(nb.idx[0]).tolist()) == {0, 1, 3}


def test_deterministic_and_independent_of_batching():
    s, g, qs, qg = make_case(3, "angle", 1500, 200, 4, seed=3)  # dense: levels 0-3, two passes
    key = jax.random.key(11)
    index = build_index_nd(s, g, k=20)
    full = search_all_nd(index, key, qs, qg)
    assert_exact(full, brute_lam(s, g, qs, qg), 20)
    again = search_all_nd(index, key, qs, qg)
    np.testing.assert_array_equal(np.asarray(full.idx), np.asarray(again.idx))
    # The first rows alone, the same rows among extra padding rows, many small chunks: same rows.
    head = search_all_nd(index, key, qs[:130], qg[:130])
    padded = search_all_nd(index, key, np.concatenate([qs, qs[:30]]), np.concatenate([qg, qg[:30]]),
                           n_queries=len(qs))
    chunk_stats = {}
    chunked = search_all_nd(index, key, qs, qg, chunk_items=64, stats=chunk_stats)
    assert chunk_stats["passes"][0]["chunks"] > 10
    for other, rows in ((head, 130), (padded, len(qs)), (chunked, len(qs))):
        for a, b in zip((full.idx, full.level, full.count), (other.idx, other.level, other.count)):
            np.testing.assert_array_equal(np.asarray(a)[:rows], np.asarray(b)[:rows])
    assert (np.asarray(padded.level)[len(qs):] == 0).all()
    other_key = search_all_nd(index, jax.random.key(12), qs, qg)
    assert (np.asarray(other_key.idx) != np.asarray(full.idx)).any()
    np.testing.assert_array_equal(np.asarray(other_key.level), np.asarray(full.level))


def test_chunk_packing_is_greedy_within_both_bounds():
    """_pack against a query-by-query loop: a chunk takes the next query while it then holds at
    most ``limit`` items and ``c`` queries (a query larger than ``limit`` gets a chunk alone)."""
    rng = np.random.default_rng(0)
    for n, limit, c in ((1, 5, 4), (500, 40, 7), (500, 400, 64), (300, 3, 1000)):
        n_it = rng.integers(0, 12, n)
        n_it[rng.integers(0, n, 3)] = limit + 5  # over the limit alone
        ref, items, rows = [], 0, 0
        for q, x in enumerate(n_it):
            if q == 0 or items + x > limit or rows + 1 > c:
                ref.append(q)
                items, rows = 0, 0
            items, rows = items + x, rows + 1
        np.testing.assert_array_equal(_pack(n_it, limit, c), ref)


def test_sampling_is_uniform():
    """One query, repeated R times in one call: every row is an independent uniform k-subset
    of the same m members, so member i appears in a row with probability p = k/m. With c_i
    the number of rows containing i, X = sum (c_i - R p)^2 / (R p (1 - p)) is ~chi-square with
    m - 1 degrees of freedom (the c_i sum to R k). Bounds: mean +- 6 standard deviations
    (sqrt(2 (m - 1))): a false alarm has probability ~1e-6; a sampler favouring some members
    by 10% (e.g. the first ranks) would give X ~ m-1 + 0.01 R p m / (1-p) ~ 110 beyond the mean."""
    rng = np.random.default_rng(5)
    n, k, reps = 600, 8, 4000
    s = rng.uniform(-1, 1, (4 * n, 2)).astype(np.float32)
    s = s[np.linalg.norm(s, axis=1) > 0.3][:n]  # nothing near the origin ...
    s[:30] = rng.uniform(-0.02, 0.02, (30, 2))  # ... but these 30 members
    g = np.zeros(n, np.float32)
    q_s = np.zeros((reps, 2), np.float32)
    nb = find_neighbours_nd(jax.random.key(3), s, g, q_s, np.zeros(reps, np.float32), k=k)
    lam = brute_lam(s, g, q_s[:1], np.zeros(1, np.float32))
    members = np.flatnonzero(lam[0] <= np.asarray(nb.level)[0])
    m = len(members)
    assert (np.asarray(nb.level) == 0).all() and m == 30 and (np.asarray(nb.count) == m).all()
    idx = np.asarray(nb.idx)
    c = np.bincount(idx.ravel(), minlength=n)
    assert c[members].sum() == reps * k and c.sum() == reps * k
    p = k / m
    x = float((((c[members] - reps * p) ** 2) / (reps * p * (1 - p))).sum())
    sd = math.sqrt(2 * (m - 1))
    assert m - 1 - 6 * sd < x < m - 1 + 6 * sd, f"chi-square {x:.1f} for {m - 1} dof"
    # Pairs too: each unordered pair appears in a row with probability k(k-1)/(m(m-1)).
    pair = np.zeros((n, n), np.int64)
    for row in idx[:1000]:
        pair[np.ix_(row, row)] += 1
    off = pair[np.ix_(members, members)][~np.eye(m, dtype=bool)]
    expect = 1000 * k * (k - 1) / (m * (m - 1))
    assert off.min() > 0.4 * expect and off.max() < 1.7 * expect  # about +-5 sd


def test_overflow_is_reported_and_rerun():
    s, g, qs, qg = make_case(3, 2, 1500, 150, 5, seed=len("ds3-vec2"))
    stats = {}
    nb = find_neighbours_nd(jax.random.key(7), s, g, qs, qg, k=20, item_capacity=8, stats=stats)
    assert stats["overflow_chunks"] > 0 and all(p["reruns"] > 0 for p in stats["passes"])
    assert_exact(nb, brute_lam(s, g, qs, qg), 20)
    ref = find_neighbours_nd(jax.random.key(7), s, g, qs, qg, k=20)
    np.testing.assert_array_equal(np.asarray(nb.idx), np.asarray(ref.idx))


@pytest.mark.parametrize("kwargs, message", [
    ({"data_s": np.zeros(10)}, "data_s must have shape"),
    ({"data_s": np.zeros((30, 11))}, "1 <= d_s <= 10"),
    ({"query_s": np.zeros((5, 2))}, "d_s=2"),
    ({"data_g": None}, "query goals"),
    ({"data_g": np.zeros((30, 2))}, "query goals"),
    ({"data_g": np.zeros((30, 2)), "query_g": np.zeros((5, 3))}, "d_g"),
    ({"data_g": np.zeros(29)}, "data_g must be None"),
    ({"query_g": np.zeros((5, 11))}, "query_g must be None"),
    ({"data_s": np.full((30, 3), np.nan)}, "NaN or inf"),
    ({"query_g": np.array([0, 0, np.inf, 0, 0])}, "NaN or inf"),
    ({"k": 31}, "at least k=31"),
    ({"k": 0}, "positive int"),
    ({"k": 2.5}, "positive int"),
    ({"radius_s": 0.0}, "radius_s"),
    ({"radius_g": -1.0}, "radius_g"),
    ({"radius_s": float("inf")}, "radius_s"),
    ({"growth": 1.0}, "growth"),
    ({"growth": float("nan")}, "growth"),
    ({"growth": 1 + 1e-7, "data_s": np.arange(90.0).reshape(30, 3)}, "too close to 1"),
    ({"grid": ((3, 1.0),)}, "last grid axis"),
    ({"grid": ((7, 1.0),)}, "grid must list"),
    ({"grid": ((0, 1.0, 3),)}, "grid must list"),
    ({"grid": ((0, 1.0), (1, 1.0, 2))}, "grid must list"),
])
def test_errors(kwargs, message):
    args = {"data_s": np.zeros((30, 3)), "data_g": np.zeros(30), "query_s": np.zeros((5, 3)),
            "query_g": np.zeros(5), "k": 5}
    args.update(kwargs)
    with pytest.raises(ValueError, match=message):
        find_neighbours_nd(jax.random.key(0), **args)
