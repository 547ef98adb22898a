"""Jittable general-space queries (neighbours.query) against the NumPy reference: the scan
(reference / fallback) and the policy index (bounded stencils, phases, overflow, seeds
stacked for vmap); the dispatch of find_neighbours by shape, and a 3-D task learned
through the public API."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lazyq_jax as lq
from lazyq_jax.neighbours.common import wrap_angle
from lazyq_jax.neighbours.nd import find_neighbours_nd, membership_level_reference
from lazyq_jax.neighbours.query import (_scan_query, build_policy_index, build_scan_index,
                                        query_neighbours_scan, query_policy, stack_policy_indices)
from lazyq_jax.neighbours.scan import _wrap_jit

RS, RG, GROWTH, MAX_LEVEL = 0.1, 0.4, 2 ** (1 / 3), 8


def _case(rng, n, q, d_s, goal):
    s = rng.uniform(-1, 1, (n, d_s)).astype(np.float32)
    qs = rng.uniform(-1, 1, (q, d_s)).astype(np.float32)
    if goal == "angle":  # in [-pi, pi): wrapping is exact; queries near +-pi test the wrap-around
        g = rng.uniform(-np.pi, np.pi, n).astype(np.float32)
        qg = np.concatenate([np.full(q // 2, np.float32(3.1)), rng.uniform(-np.pi, np.pi, q - q // 2)])
        return s, g, qs, qg.astype(np.float32)
    if goal == "vector":
        return s, rng.uniform(-1, 1, (n, 2)).astype(np.float32), qs, rng.uniform(-1, 1, (q, 2)).astype(np.float32)
    return s, None, qs, None


def reference(s, g, qs, qg, k, max_level, rs=RS, rg=RG, n_valid=None):
    """``(lam [Q, N], level [Q] (-1 beyond max_level), count [Q])`` of the float32 formula."""
    n_valid = len(s) if n_valid is None else n_valid
    lam = membership_level_reference(s[:n_valid], None if g is None else g[:n_valid], qs, qg, radius_s=rs,
                                     radius_g=rg, growth=GROWTH, max_level=max_level)
    kth = np.sort(lam, axis=1)[:, k - 1]
    level = np.where(kth <= max_level, kth, -1)
    count = np.where(level >= 0, (lam <= level[:, None]).sum(1), (lam <= max_level).sum(1))
    return lam, level, count


def assert_exact(nb, lam, level, count, k, rows=None):
    """Levels and counts equal; k distinct members of B_level (idx -1 where level -1)."""
    rows = np.arange(len(level)) if rows is None else rows
    idx, lv, cnt = (np.asarray(a)[rows] for a in (nb.idx, nb.level, nb.count))
    np.testing.assert_array_equal(lv, level[rows])
    np.testing.assert_array_equal(cnt, count[rows])
    for i, r in enumerate(rows):
        if level[r] < 0:
            assert (idx[i] == -1).all()
        else:
            assert len(set(idx[i].tolist())) == k, "indices not distinct"
            assert (lam[r, idx[i]] <= level[r]).all(), "sampled a non-member"


# ----------------------------------------------------------------------------- scan


@pytest.mark.parametrize("d_s, goal, k", [(3, "angle", 5), (1, None, 400), (4, "vector", 12), (2, "vector", 40)])
def test_scan_query_matches_the_reference(d_s, goal, k):
    rng = np.random.default_rng(d_s)
    s, g, qs, qg = _case(rng, 3000, 40, d_s, goal)
    index = build_scan_index(s, g, k=k, radius_s=RS, radius_g=RG, growth=GROWTH, max_level=MAX_LEVEL)
    nb = jax.jit(query_neighbours_scan)(index, jax.random.PRNGKey(0), qs, qg)
    lam, level, count = reference(s, g, qs, qg, k, MAX_LEVEL)
    assert (level >= 0).any() and (level > 0).any()  # the case exercises growth
    assert_exact(nb, lam, level, count, k)


def test_scan_query_samples_uniformly():
    # One query, m members at its level: each member drawn with probability k / m.
    rng = np.random.default_rng(7)
    s = rng.uniform(-1, 1, (400, 3)).astype(np.float32)
    index = build_scan_index(s, None, k=6, radius_s=0.5, growth=GROWTH, max_level=MAX_LEVEL)
    q = np.zeros((1, 3), np.float32)
    draws = jax.jit(jax.vmap(lambda key: query_neighbours_scan(index, key, q).idx[0]))(
        jax.random.split(jax.random.PRNGKey(3), 4000))
    lam = membership_level_reference(s, None, q, None, radius_s=0.5, growth=GROWTH)[0]
    members = np.flatnonzero(lam <= np.sort(lam)[5])
    hits = np.bincount(np.asarray(draws).ravel(), minlength=400)
    assert hits[np.setdiff1d(np.arange(400), members)].sum() == 0
    p = 6 / members.size
    expected, sd = 4000 * p, np.sqrt(4000 * p * (1 - p))
    assert np.abs(hits[members] - expected).max() < 5 * sd, (hits[members], expected)


def test_scan_query_errors():
    s = np.zeros((50, 3), np.float32)
    with pytest.raises(ValueError, match="k=60"):
        build_scan_index(s, None, k=60)
    index = build_scan_index(s, None, k=5)
    with pytest.raises(ValueError, match=r"\[Q, 3\]"):
        query_neighbours_scan(index, jax.random.PRNGKey(0), np.zeros((2, 2), np.float32))
    with pytest.raises(ValueError, match="no goals"):
        query_neighbours_scan(index, jax.random.PRNGKey(0), np.zeros((2, 3), np.float32), np.zeros(2))
    with pytest.raises(ValueError, match="NaN"):
        build_scan_index(np.full((50, 3), np.nan, np.float32), None, k=5)


# ----------------------------------------------------------------------------- policy index


def test_jitted_wrap_is_numpys():
    # Around every multiple of pi up to 200 turns, a few ulps either side, and random angles.
    base = (np.arange(-400, 401) * np.float64(np.pi)).astype(np.float32)
    g = base
    for _ in range(3):
        g = np.concatenate([g, np.nextafter(g, np.float32(np.inf)), np.nextafter(g, -np.float32(np.inf))])
    g = np.concatenate([g, np.random.default_rng(0).uniform(-1500, 1500, 20000).astype(np.float32)])
    g = g[np.abs(g) > 1e-30]  # subnormals: XLA flushes them to zero
    np.testing.assert_array_equal(np.asarray(jax.jit(_wrap_jit)(jnp.asarray(g))), wrap_angle(g))


def _policy_case(d_s, goal, n, q, spread, seed):
    """Data uniform in a box of ``spread`` state radii a side, angle goals crowding +-pi (or
    goal vectors); queries: data points, points moved by about a radius, a few anywhere
    (some beyond max_level), angles near and beyond +-pi (wrap-around)."""
    rng = np.random.default_rng(seed)
    s = (rng.uniform(-0.5, 0.5, (n, d_s)) * spread * RS).astype(np.float32)
    pick = rng.integers(0, n, q)
    qs = s[pick] + rng.normal(0, RS, (q, d_s)).astype(np.float32) * (np.arange(q) % 3 > 0)[:, None]
    qs[-4:] = rng.uniform(-0.7, 0.7, (4, d_s)) * spread * RS
    qs[-2:] += 4 * spread * RS  # far outside the data: beyond max_level
    qs = qs.astype(np.float32)
    if goal == "angle":
        g = (np.pi - rng.uniform(-1.2, 1.2, n)).astype(np.float32)
        g = np.where(g > np.pi, g - 2 * np.pi, g).astype(np.float32)
        qg = g[pick] + rng.normal(0, RG / 2, q).astype(np.float32)
        qg[:6] = [np.pi, -np.pi, np.nextafter(np.float32(np.pi), np.float32(0)), 3 * np.pi, -7.0, 9.5]
        return s, g, qs, qg.astype(np.float32)
    if goal == "vector":
        g = (rng.uniform(-0.5, 0.5, (n, 2)) * 4 * RG).astype(np.float32)
        return s, g, qs, (g[pick] + rng.normal(0, RG / 2, (q, 2))).astype(np.float32)
    return s, None, qs, None


# name: (d_s, goal, n, q, spread, k, max_level, schedule, grid); None: chosen by the build.
POLICY_CASES = {
    "ds1-vector": (1, "vector", 2500, 48, 60, 20, 6, None, None),
    # Sparse: levels up to 8 and beyond, k above most base neighbourhoods, two phases,
    # angles at and beyond +-pi.
    "ds3-angle-sparse-2phases": (3, "angle", 2500, 64, 9, 30, 8, (3, 8), None),
    # Too few points for a 5-D grid to pay (the build picks the scan): a forced grid.
    "ds5-none-k40": (5, None, 2500, 48, 2.5, 40, 6, (6,), ((0, RS), (1, RS), (2, RS / 2))),
    "ds2-angle-scan-only": (2, "angle", 1500, 48, 8, 20, 6, None, ()),
}


@pytest.mark.parametrize("name", sorted(POLICY_CASES))
def test_policy_query_matches_the_reference(name):
    d_s, goal, n, q, spread, k, max_level, schedule, grid = POLICY_CASES[name]
    s, g, qs, qg = _policy_case(d_s, goal, n, q, spread, seed=len(name))
    index = build_policy_index(s, g, k=k, radius_s=RS, radius_g=RG, growth=GROWTH, max_level=max_level,
                               schedule=schedule, grid=grid)
    assert bool(index.grid) == (grid != ()), "a grid beats the scan on these data"
    if schedule is not None and grid != ():
        assert [p.hi for p in index.phases] == list(schedule)
    elif grid is None:
        assert len(index.phases) >= 2, index.phases
    # A non-finite query (inside jit: no members, not an overflow) rides along.
    qs_nan = np.concatenate([qs, np.full((1, d_s), np.nan, np.float32)])
    qg_nan = None if g is None else np.concatenate([qg, np.zeros((1, *qg.shape[1:]), np.float32)])
    run = jax.jit(query_policy)
    nb = run(index, jax.random.PRNGKey(1), jnp.asarray(qs_nan), None if qg_nan is None else jnp.asarray(qg_nan))
    lam, level, count = reference(s, g, qs, qg, k, max_level)
    assert_exact(nb, lam, level, count, k, rows=np.arange(q))
    assert int(nb.level[q]) == -1 and int(nb.count[q]) == 0 and (np.asarray(nb.idx[q]) == -1).all()
    assert not np.asarray(nb.overflow).any(), "queries near the data fit the default capacities"
    assert (level == -1).any() and (level >= 0).mean() > 0.5 and (level > 0).any(), np.bincount(level + 1)
    if "sparse" in name:
        assert level.max() > 3 and (level > 3).mean() > 0.2, np.bincount(level + 1)
        base = (lam == 0).sum(1)
        assert (base < k).mean() > 0.5, "k should exceed most base neighbourhoods"
    # Deterministic in the key; another key draws other members at the same levels.
    again = run(index, jax.random.PRNGKey(1), jnp.asarray(qs_nan), None if qg_nan is None else jnp.asarray(qg_nan))
    np.testing.assert_array_equal(np.asarray(again.idx), np.asarray(nb.idx))


def test_policy_overflow_is_reported_and_exact():
    # Phase 0's pool holds 2 items a query: the queries run in rounds (smallest stencils
    # first), all fit.  Phase 1 has 8 slots of 1 item: its queries run in rounds of 8, and
    # those whose stencil exceeds the pool overflow: flagged, answered by the scan (exact),
    # or left at level -1 (still flagged) without the fallback.
    s, g, qs, qg = _policy_case(3, "angle", 2500, 64, 9, seed=3)
    k, max_level = 30, 8
    lam, level, count = reference(s, g, qs, qg, k, max_level)
    index = build_policy_index(s, g, k=k, radius_s=RS, radius_g=RG, growth=GROWTH, max_level=max_level,
                               schedule=(2, (max_level, 0.01)), capacity=(2, 1))
    assert index.phases[1].slots(64) == 8
    key = jax.random.PRNGKey(0)
    run = jax.jit(query_policy)
    nb = run(index, key, qs, qg)
    over = np.asarray(nb.overflow)
    assert 0.2 < over.mean() < 0.95 and not over[level.clip(0) <= 2].any(), over.mean()
    assert_exact(nb, lam, level, count, k)
    lossy = run(index, key, qs, qg, fallback=False)  # a traced flag: the same compiled query
    np.testing.assert_array_equal(np.asarray(lossy.overflow), over)
    assert (np.asarray(lossy.level)[over] == -1).all() and (np.asarray(lossy.idx)[over] == -1).all()
    fit = ~over  # the queries that fit are the same with or without the fallback
    np.testing.assert_array_equal(np.asarray(lossy.idx)[fit], np.asarray(nb.idx)[fit])
    np.testing.assert_array_equal(np.asarray(lossy.level)[fit], level[fit])


def test_policy_stacked_seeds_vmap_equals_each_seed():
    # Two datasets of different sizes padded to one length: padding rows are copies of the
    # queries (members if they were counted).  Built separately (different grids), stacked
    # (one layout), queried under vmap: each seed's rows equal its own query on its slice of
    # the stack and the reference of its valid rows.
    k, max_level, n_rows = 20, 6, 2500
    seeds = []
    for seed, (n, spread) in enumerate(((2500, 2.5), (1700, 2))):
        s, g, qs, qg = _policy_case(5, "angle", n, 40, spread, seed=10 + seed)
        pad = n_rows - n
        s_pad = np.concatenate([s, qs[np.arange(pad) % len(qs)]])
        g_pad = np.concatenate([g, qg[np.arange(pad) % len(qg)]])
        index = build_policy_index(s_pad, g_pad, k=k, radius_s=RS, radius_g=RG, growth=GROWTH,
                                   max_level=max_level, n_valid=n, schedule=(max_level,),
                                   grid=((5, 2 * RG), (0, RS), (1, RS / (1 + seed))))
        seeds.append((s_pad, g_pad, qs, qg, n, index))
    assert seeds[0][-1].grid != seeds[1][-1].grid
    stacked = stack_policy_indices([x[-1] for x in seeds])  # one layout: the second is rebuilt
    assert stacked.orig.shape[0] == 2 and stacked.n_entries.shape == (2,)
    assert [ax.width for ax in stacked.grid] == [ax.width for ax in seeds[0][-1].grid]
    keys = jax.random.split(jax.random.PRNGKey(4), 2)
    qs2 = jnp.asarray(np.stack([x[2] for x in seeds]))
    qg2 = jnp.asarray(np.stack([x[3] for x in seeds]))
    nb = jax.jit(jax.vmap(query_policy))(stacked, keys, qs2, qg2)
    one = jax.jit(query_policy)
    for i, (s, g, qs, qg, n, own) in enumerate(seeds):
        own_nb = one(jax.tree.map(lambda x, i=i: x[i], stacked), keys[i], qs2[i], qg2[i])
        for a, b in zip((nb.idx, nb.level, nb.count, nb.overflow),
                        (own_nb.idx, own_nb.level, own_nb.count, own_nb.overflow)):
            np.testing.assert_array_equal(np.asarray(a)[i], np.asarray(b))
        lam, level, count = reference(s, g, qs, qg, k, max_level, n_valid=n)
        assert (level > 0).any()
        assert_exact(jax.tree.map(lambda x, i=i: x[i], nb), lam, level, count, k)
        assert (np.asarray(nb.idx)[i] < n).all(), "a padding row was drawn"


def chi_square_ok(idx, members, k):
    """Rows independent uniform k-subsets of ``members``: member i is in a row with probability
    p = k/m; with c_i the rows holding i, X = sum (c_i - R p)^2 / (R p (1 - p)) is ~chi-square
    with m - 1 degrees of freedom; bounds mean +- 6 sd (a false alarm ~1e-6; a sampler
    favouring some members by 10% gives X ~ m - 1 + 0.01 R p m / (1 - p), ~60 beyond)."""
    reps, m = idx.shape[0], len(members)
    c = np.bincount(idx.ravel(), minlength=max(members) + 1)
    assert c[members].sum() == reps * k == c.sum(), "a non-member was drawn"
    p = k / m
    x = float((((c[members] - reps * p) ** 2) / (reps * p * (1 - p))).sum())
    sd = math.sqrt(2 * (m - 1))
    assert m - 1 - 6 * sd < x < m - 1 + 6 * sd, f"chi-square {x:.1f} for {m - 1} dof"


def test_stacking_like_an_earlier_index_keeps_its_shapes_and_the_results():
    # Online rounds: the policy of round r+1 is stacked "like" round r's, so that the rollout
    # compiled for round r runs it.  On the same layout every capacity is at least like's
    # (one that must grow becomes a power of two), the jitted query does not recompile, and
    # the results equal those of the index stacked without like (capacities bound the work,
    # not the result).  A like on another layout is ignored.
    k, max_level = 20, 6
    s, g, qs, qg = _policy_case(2, "angle", 3000, 48, 3, seed=21)
    grid = ((2, 2 * RG), (0, RS), (1, RS))
    build = lambda n, cap: build_policy_index(s, g, k=k, radius_s=RS, radius_g=RG, growth=GROWTH,
                                              max_level=max_level, grid=grid, schedule=(1, max_level),
                                              capacity=cap, n_valid=n)
    small = stack_policy_indices([build(1500, [3, 5])])
    assert small.orig.shape == (1, 3000)  # entries padded to the rows: half of them valid
    plain = stack_policy_indices([build(3000, [4, 40])])
    shapes = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype), small)  # what the agent keeps
    grown = stack_policy_indices([build(3000, [4, 40])], like=shapes)
    assert [p.cap for p in small.phases] == [3, 5]
    assert [p.cap for p in grown.phases] == [4, 64]  # grown past like's: powers of two
    kept = stack_policy_indices([build(3000, [2, 4])], like=grown)  # needs less: like's shapes
    assert [p.cap for p in kept.phases] == [4, 64]
    assert jax.tree.structure(kept) == jax.tree.structure(grown)
    assert [x.shape for x in jax.tree.leaves(kept)] == [x.shape for x in jax.tree.leaves(grown)]
    run = jax.jit(jax.vmap(query_policy, in_axes=(0, None, None, None)))
    key = jax.random.PRNGKey(5)
    ref, *others = [run(index, key, jnp.asarray(qs), jnp.asarray(qg)) for index in (plain, grown, kept)]
    assert run._cache_size() == 2  # plain, then grown and kept (one shape)
    for nb in (ref, *others):
        assert not np.asarray(nb.overflow).any()
    for nb in others:
        for a, b in zip((nb.idx, nb.level, nb.count), (ref.idx, ref.level, ref.count)):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    lam, level, count = reference(s, g, qs, qg, k, max_level)
    assert_exact(jax.tree.map(lambda x: x[0], ref), lam, level, count, k)
    other = stack_policy_indices([build_policy_index(s, g, k=k, radius_s=RS, radius_g=RG, growth=GROWTH,
                                                     max_level=max_level, grid=((0, RS), (1, RS)),
                                                     schedule=(1, max_level), capacity=[2, 4])], like=grown)
    assert [p.cap for p in other.phases] == [2, 4]  # another grid: like ignored


def test_policy_samples_uniformly():
    # One query at the origin with 30 members (k = 8): R rows through the phase pool (one
    # batch of R copies: independent draws) and through the fallback scan (R keys).
    rng = np.random.default_rng(5)
    n, k, reps = 600, 8, 3000
    s = rng.uniform(-1, 1, (4 * n, 2)).astype(np.float32)
    s = s[np.linalg.norm(s, axis=1) > 0.3][:n]  # nothing near the origin ...
    s[:30] = rng.uniform(-0.02, 0.02, (30, 2))  # ... but these 30 members
    index = build_policy_index(s, None, k=k, radius_s=0.05, radius_g=RG, growth=GROWTH, max_level=2,
                               grid=((0, 0.05), (1, 0.03)))  # 600 points: the build would scan
    assert index.grid and len(index.phases) == 1
    pooled = jax.jit(query_policy)(index, jax.random.PRNGKey(3), np.zeros((reps, 2), np.float32))
    assert not np.asarray(pooled.overflow).any()
    seeds = jnp.arange(reps, dtype=jnp.uint32) * jnp.uint32(0x9E3779B9)
    scanned = jax.jit(jax.vmap(lambda sd: _scan_query(index, sd, jnp.zeros(2))))(seeds)
    for idx, level, count in ((pooled.idx, pooled.level, pooled.count), scanned):
        assert (np.asarray(level) == 0).all() and (np.asarray(count) == 30).all()
        chi_square_ok(np.asarray(idx), np.arange(30), k)


@pytest.mark.parametrize("kwargs, message", [
    ({"data_s": np.zeros(10)}, "data_s must have shape"),
    ({"data_s": np.zeros((30, 11))}, "1 <= d_s <= 10"),
    ({"data_g": np.zeros(29)}, "data_g must be None"),
    ({"data_g": np.zeros((30, 11))}, "data_g must be None"),
    ({"data_s": np.full((30, 3), np.nan)}, "NaN or inf"),
    ({"data_g": np.full(30, np.inf)}, "NaN or inf"),
    ({"k": 31}, "at least k=31"),
    ({"n_valid": 10, "k": 11}, "at least k=11"),
    ({"n_valid": 31}, "n_valid"),
    ({"k": 0}, "positive int"),
    ({"radius_s": 0.0}, "radius_s"),
    ({"growth": 1.0}, "growth"),
    ({"max_level": -1}, "max_level"),
    ({"max_level": 2.0}, "max_level"),
    ({"schedule": (1, 2)}, "schedule"),
    ({"schedule": ((1, 0.0), 3)}, "schedule"),
    ({"capacity": 0}, "capacity"),
    ({"capacity": (4, 4)}, "capacity per phase needs schedule"),
    ({"capacity": (4, 4), "schedule": (3,)}, "capacity per phase"),
    ({"grid": ((3, 0.1),)}, "last grid axis"),
    ({"grid": ((7, 0.1),)}, "grid must list"),
])
def test_policy_build_errors(kwargs, message):
    args = {"data_s": np.zeros((30, 3)), "data_g": np.zeros(30), "k": 5, "radius_s": RS, "radius_g": RG,
            "growth": GROWTH, "max_level": 3}
    args.update(kwargs)
    data_s, data_g = args.pop("data_s"), args.pop("data_g")
    with pytest.raises(ValueError, match=message):
        build_policy_index(data_s, data_g, **args)


def test_policy_query_and_stack_errors():
    rng = np.random.default_rng(0)
    s, g = rng.uniform(-1, 1, (40, 3)).astype(np.float32), rng.uniform(-3, 3, 40).astype(np.float32)
    s[35:] = np.nan  # padding may hold anything
    kw = {"k": 5, "radius_s": RS, "radius_g": RG, "growth": GROWTH, "max_level": 3}
    index = build_policy_index(s, g, n_valid=35, **kw)
    key = jax.random.PRNGKey(0)
    with pytest.raises(ValueError, match=r"\[Q, 3\]"):
        query_policy(index, key, np.zeros((2, 2), np.float32), np.zeros(2, np.float32))
    with pytest.raises(ValueError, match="angles"):
        query_policy(index, key, np.zeros((2, 3), np.float32))
    with pytest.raises(ValueError, match="angles"):
        query_policy(index, key, np.zeros((2, 3), np.float32), np.zeros((2, 1), np.float32))
    with pytest.raises(ValueError, match="NaN"):
        query_policy(index, key, np.full((2, 3), np.nan, np.float32), np.zeros(2, np.float32))
    with pytest.raises(ValueError, match="NaN"):
        query_policy(index, key, np.zeros((2, 3), np.float32), np.array([0, np.inf], np.float32))
    none = build_policy_index(s[:35], None, **kw)
    with pytest.raises(ValueError, match="no goals"):
        query_policy(none, key, np.zeros((2, 3), np.float32), np.zeros(2, np.float32))
    with pytest.raises(ValueError, match="n_rows"):
        stack_policy_indices([index, build_policy_index(s[:35], g[:35], **kw)])
    with pytest.raises(ValueError, match="max_level"):
        stack_policy_indices([index, build_policy_index(s, g, n_valid=35, **{**kw, "max_level": 4})])
    stacked = stack_policy_indices([index, index])
    with pytest.raises(ValueError, match="seed axis"):
        stack_policy_indices([stacked, stacked])


# ----------------------------------------------------------------------------- dispatch, end to end


def test_find_neighbours_dispatches_by_shape():
    rng = np.random.default_rng(1)
    s, g, qs, qg = _case(rng, 2000, 30, 3, "vector")
    key = jax.random.PRNGKey(5)
    a = lq.find_neighbours(key, s, g, qs, qg, k=8, radius_s=RS, radius_g=RG)
    b = find_neighbours_nd(key, s, g, qs, qg, k=8, radius_s=RS, radius_g=RG)
    for x, y in zip((a.idx, a.level, a.count), (b.idx, b.level, b.count)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_a_3d_task_is_learned_through_the_public_api():
    # States in R^3, actions of length c on the 3-D sphere, no goal: +1 (and the end)
    # for reaching the ball of radius 0.15 around the origin.  The optimal action
    # points at the origin, -c s / |s|: the lazy policy (Eq. 9) must find it from
    # random data through find_neighbours, make_train and make_lazy_policy.
    rng = np.random.default_rng(0)
    n, c = 30000, 0.1
    s = rng.uniform(-0.6, 0.6, (int(1.1 * n), 3)).astype(np.float32)
    s = s[np.linalg.norm(s, axis=1) > 0.15][:n]
    a = rng.normal(size=s.shape)
    a = (c * a / np.linalg.norm(a, axis=1, keepdims=True)).astype(np.float32)
    done = np.linalg.norm(s + a, axis=1) < 0.15
    data = lq.Transitions(s=jnp.asarray(s), a=jnp.asarray(a), s_next=jnp.asarray(s + a),
                          r=jnp.asarray(done, jnp.float32), g=None, done=jnp.asarray(done))
    idx = lq.find_neighbours(jax.random.PRNGKey(0), data.s, None, data.s, None, k=40, radius_s=0.08).idx
    assert idx.shape == (n, 40)
    trainer = lq.make_train(lq.TrainConfig(cycles=5, epochs=4, width=32, batch_size=512), c,
                            state_dim=3, goal=None, state_scale=0.6)
    state, metrics = jax.jit(trainer.train)(jax.random.PRNGKey(1), data, idx)
    assert np.all(np.isfinite(np.asarray(metrics["loss"])))
    policy = lq.make_lazy_policy(trainer.value_fn(state), data, gamma=0.9, action_length=c, k=40,
                                 radius_s=0.08)
    test = rng.normal(size=(200, 3))
    test = (test / np.linalg.norm(test, axis=1, keepdims=True) * rng.uniform(0.25, 0.4, (200, 1)))
    act, _, found = jax.jit(lq.lazy_policy)(policy, jax.random.PRNGKey(2), jnp.asarray(test, jnp.float32), None)
    act = np.asarray(act)
    assert np.asarray(found).all()
    np.testing.assert_allclose(np.linalg.norm(act, axis=1), c, rtol=1e-5)
    cos = np.sum(act * -test, axis=1) / (c * np.linalg.norm(test, axis=1))
    good = np.mean(cos > np.cos(np.radians(26)))
    assert good > 0.8, good  # 0.985 seen; 0.66 with 10k points, radius 0.12, k = 20
