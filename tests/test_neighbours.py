"""Neighbour search against a brute-force NumPy reference (same float32 formula)."""

import contextlib

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lazyq_jax.neighbours.common import TWO_PI
from lazyq_jax.neighbours import (
    Neighbours,
    build_index,
    build_scan_index,
    check_found,
    find_neighbours,
    query_neighbours,
    query_neighbours_scan,
    radius_tables,
    search_all,
    wrap_angle,
)
from lazyq_jax.neighbours.query import build_policy_index, query_policy

RS, RG, G = 0.06, 0.1, 2 ** (1 / 3)


def brute(s, g, qs, qg, k, rs=RS, rg=RG, growth=G):
    """(level [Q], |B_level| [Q], membership level lam [Q, N]) by the documented float32 formula."""
    r2s, rgl = radius_tables(rs, rg, growth, np.arange(200))
    dx = s[None, :, 0] - qs[:, None, 0]
    dy = s[None, :, 1] - qs[:, None, 1]
    d = np.abs(wrap_angle(g)[None, :] - wrap_angle(qg)[:, None])
    lam = np.maximum(np.searchsorted(r2s, (dx * dx + dy * dy).ravel(), side="right"),
                     np.searchsorted(rgl, np.minimum(d, TWO_PI - d).ravel(), side="right")).reshape(d.shape)
    level = np.partition(lam, k - 1, axis=1)[:, k - 1]
    return level, (lam <= level[:, None]).sum(1), lam


def assert_exact(nb, s, g, qs, qg, k, **kw):
    level, count, lam = brute(s, g, qs, qg, k, **kw)
    idx = np.asarray(nb.idx)
    chex.assert_shape(nb.idx, (len(qs), k))
    np.testing.assert_array_equal(np.asarray(nb.level), level)
    np.testing.assert_array_equal(np.asarray(nb.count), count)
    assert (np.take_along_axis(lam, idx, 1) <= level[:, None]).all(), "sampled a non-member"
    assert all(len(set(row)) == k for row in idx.tolist()), "indices not distinct"
    return level


@pytest.fixture(scope="module")
def wrap_data():
    """Dense in a small square, goals only within 0.6 of +-pi: levels 0-3 occur and every
    neighbourhood depends on the wrap-around."""
    rng = np.random.default_rng(0)
    n = 4000
    s = rng.uniform(-0.3, 0.3, (n, 2)).astype(np.float32)
    g = (np.pi - rng.uniform(-0.6, 0.6, n)).astype(np.float32)  # some above pi: wrapped internally
    q = np.concatenate([np.arange(300), rng.integers(0, n, 50)])
    qs = np.concatenate([s[q[:300]], rng.uniform(-0.45, 0.45, (50, 2)).astype(np.float32)])
    qg = np.concatenate([g[q[:300]], rng.uniform(-np.pi, np.pi, 50).astype(np.float32)])
    return s, g, qs, qg


def test_find_neighbours_matches_brute_force_with_growth_and_wrap(wrap_data):
    s, g, qs, qg = wrap_data
    nb = find_neighbours(jax.random.key(0), s, g, qs, qg, k=20)
    level = assert_exact(nb, s, g, qs, qg, 20)
    counts = np.bincount(level)
    assert len(counts) >= 5 and (counts[:4] > 0).all(), f"want levels 0..3 and beyond, got {counts}"


def test_wrap_around_pi():
    s = np.array([[0.0, 0.0]] * 3 + [[0.0, 0.0]], np.float32)
    g = np.array([np.pi - 0.02, -np.pi + 0.03, 0.0, np.pi], np.float32)
    nb = find_neighbours(jax.random.key(1), s, g, s[:1], np.array([-np.pi + 0.01], np.float32), k=3)
    assert int(nb.level[0]) == 0 and int(nb.count[0]) == 3
    assert set(np.asarray(nb.idx[0]).tolist()) == {0, 1, 3}


def test_query_neighbours_jit_matches_host_and_brute_force(wrap_data):
    s, g, qs, qg = wrap_data
    index = build_index(s, g, k=20, max_level=16)
    key = jax.random.key(3)
    eager = query_neighbours(index, key, jnp.asarray(qs), jnp.asarray(qg))
    jitted = jax.jit(query_neighbours)(index, key, jnp.asarray(qs), jnp.asarray(qg))
    check_found(jitted)
    assert_exact(jitted, s, g, qs, qg, 20)
    chex.assert_trees_all_equal(eager, jitted)
    again = jax.jit(query_neighbours)(index, key, jnp.asarray(qs), jnp.asarray(qg))
    chex.assert_trees_all_equal(jitted, again)
    other = jax.jit(query_neighbours)(index, jax.random.key(4), jnp.asarray(qs), jnp.asarray(qg))
    np.testing.assert_array_equal(other.level, jitted.level)
    assert (np.asarray(other.idx) != np.asarray(jitted.idx)).any()


def test_query_inside_scan_of_a_rollout(wrap_data):
    s, g, _, _ = wrap_data
    index = build_index(s, g, k=5, max_level=6)

    goals = jnp.asarray(g[:4])  # the data's goals lie near +-pi

    def step(carry, key):
        nb = query_neighbours(index, key, carry, goals)
        return carry + 0.01, (nb.idx, nb.level)

    keys = jax.random.split(jax.random.key(0), 3)
    start = jnp.asarray(s[:4])
    _, (idx, levels) = jax.jit(lambda ks: jax.lax.scan(step, start, ks))(keys)
    chex.assert_shape(levels, (3, 4))
    # the same queries outside scan/jit give the same (exact) neighbourhoods
    for t in range(3):
        q = np.asarray(start) + 0.01 * t
        nb = query_neighbours(index, keys[t], jnp.asarray(q), goals)
        np.testing.assert_array_equal(np.asarray(nb.idx), np.asarray(idx[t]))
        np.testing.assert_array_equal(np.asarray(nb.level), np.asarray(levels[t]))
        assert np.all(np.asarray(nb.level) >= 0)
        assert_exact(nb, s, g, q.astype(np.float32), g[:4], 5)


def test_level_beyond_max_level_is_reported_not_dropped(wrap_data):
    s, g, _, _ = wrap_data
    index = build_index(s, g, k=20, max_level=0)
    far = jnp.array([[0.6, 0.6], [0.0, 0.0]], jnp.float32)  # ~0.4 from the data: level ~8
    nb = query_neighbours(index, jax.random.key(0), far, jnp.array([np.pi, np.pi], jnp.float32))
    assert int(nb.level[0]) == -1 and (np.asarray(nb.idx[0]) == -1).all()
    assert not bool(nb.found[0])
    with pytest.raises(ValueError, match="max_level"):
        check_found(nb)
    # find_neighbours has no limit: the same far query gets its exact (large) level.
    host = find_neighbours(jax.random.key(0), s, g, np.asarray(far), np.array([np.pi, np.pi], np.float32))
    assert_exact(host, s, g, np.asarray(far), np.array([np.pi, np.pi], np.float32), 20)


def test_crowded_cells_are_exact():
    """Hundreds of points in one cell and at one location: no per-cell capacity to overflow."""
    rng = np.random.default_rng(5)
    s = np.concatenate([np.zeros((600, 2)), rng.uniform(-1, 1, (400, 2))]).astype(np.float32)
    g = np.concatenate([np.full(600, 0.5), rng.uniform(-np.pi, np.pi, 400)]).astype(np.float32)
    qs = np.concatenate([s[:5], s[600:640]])
    qg = np.concatenate([g[:5], g[600:640]])
    nb = find_neighbours(jax.random.key(0), s, g, qs, qg, k=7)
    assert_exact(nb, s, g, qs, qg, 7)
    assert (np.asarray(nb.count[:5]) >= 600).all()
    index = build_index(s, g, k=7, max_level=3)
    assert index.max_window >= 600  # the static capacity was read from the data
    jq = query_neighbours(index, jax.random.key(1), jnp.asarray(qs[:5]), jnp.asarray(qg[:5]))
    assert_exact(jq, s, g, qs[:5], qg[:5], 7)


def test_sampling_is_uniform_without_replacement():
    """One neighbourhood of m = 30 points, k = 6, 6000 draws: inclusion counts ~ Binomial."""
    rng = np.random.default_rng(2)
    m, k, n_draws = 30, 6, 6000
    s = np.concatenate([rng.uniform(-0.01, 0.01, (m, 2)), rng.uniform(2, 3, (20, 2))]).astype(np.float32)
    g = np.zeros(m + 20, np.float32)
    index = build_index(s, g, k=k, max_level=0)
    nb = jax.jit(query_neighbours)(index, jax.random.key(0), jnp.zeros((n_draws, 2)), jnp.zeros(n_draws))
    idx = np.asarray(nb.idx)
    assert (np.asarray(nb.count) == m).all() and idx.max() < m
    assert all(len(set(r)) == k for r in idx[:500].tolist())
    freq = np.bincount(idx.ravel(), minlength=m)
    expected = n_draws * k / m
    chi2 = ((freq - expected) ** 2 / expected).sum()
    assert chi2 < 70, f"chi-square {chi2:.1f} with {m - 1} dof"  # p ~ 4e-5 under uniformity
    # Pairs are uniform too (sampling without replacement): spot-check one pair's rate.
    both = ((idx == 0).any(1) & (idx == 1).any(1)).mean()
    assert abs(both - k * (k - 1) / (m * (m - 1))) < 0.015


@pytest.mark.parametrize("kw, match", [
    ({"k": 0}, "k must be"), ({"k": 2.5}, "k must be"), ({"k": 11}, "at least k"),
    ({"radius_s": -0.1}, "radius_s"), ({"radius_g": 0.0}, "radius_g"), ({"growth": 1.0}, "growth"),
    ({"growth": float("nan")}, "growth"),
])
def test_bad_parameters_raise(kw, match):
    s = np.zeros((10, 2), np.float32)
    args = {"k": 3} | kw
    with pytest.raises(ValueError, match=match):
        find_neighbours(jax.random.key(0), s, np.zeros(10), s, np.zeros(10), **args)


def test_bad_points_raise():
    s, g = np.zeros((10, 2), np.float32), np.zeros(10, np.float32)
    bad_s = s.copy()
    bad_s[3, 1] = np.nan
    for args, match in [((bad_s, g, s, g), "NaN"), ((s, g, s, np.full(10, np.inf)), "NaN"),
                        ((s[:, :1], g, s, g), "d_s=1"), ((s, g[:5], s, g), "match"),
                        ((s, g, s, g[:4]), "match")]:
        with pytest.raises(ValueError, match=match):
            find_neighbours(jax.random.key(0), *args, k=3)


def test_neighbours_is_a_pytree():
    nb = Neighbours(idx=jnp.zeros((2, 3), jnp.int32), level=jnp.zeros(2, jnp.int32), count=jnp.ones(2, jnp.int32))
    assert len(jax.tree_util.tree_leaves(nb)) == 3


def test_cell_thresholds_reproduce_the_float64_floor_at_every_boundary():
    """The jitted build's cells: counting float32 thresholds must equal the host's float64
    ``clip(floor((v - lo) / h), 0, n - 1)`` for every float32 ``v``; checked on each cell
    boundary's float32 neighbours (where float32 arithmetic would disagree) and at random."""
    from lazyq_jax.neighbours.grid import _cell_thresholds

    rng = np.random.default_rng(0)
    for lo, h, n in [(-1.0032, 0.25 * RS * 1.001, 140), (-np.pi, 2 * np.pi / 125, 125), (0.3, 0.7, 1)]:
        edges = (lo + np.arange(n + 1) * h).astype(np.float32)
        v = np.concatenate([edges, np.nextafter(edges, np.float32(np.inf)),
                            np.nextafter(edges, np.float32(-np.inf)),
                            rng.uniform(lo - h, lo + (n + 1) * h, 2000).astype(np.float32)])
        want = np.clip(np.floor((v.astype(np.float64) - lo) / h), 0, n - 1)
        got = np.searchsorted(np.asarray(_cell_thresholds(lo, h, n)), v, side="right")
        np.testing.assert_array_equal(got, want)


def test_device_build_equals_the_host_build_bitwise():
    """``build_index(on_device=True)`` (one jitted program: a device sort) against the NumPy
    build: every array and static field, with points on cell boundaries, goals at +-pi,
    fixed bounds with padding to a capacity, and a coarsened grid."""
    rng = np.random.default_rng(3)
    h_x, h_y = 0.25 * RS * 1.001, 0.5 * RS * 1.001
    s = rng.uniform(-1, 1, (3000, 2)).astype(np.float32)
    s[:120, 0] = (-1 + np.arange(120) * h_x).astype(np.float32)  # on the x-cell edges
    s[200:260, 1] = np.nextafter((-1 + np.arange(60) * h_y).astype(np.float32), np.float32(-2))
    s[400] = (-1, -1)  # the lowest point: x0, y0 of the unbounded grid
    g = rng.uniform(-np.pi, np.pi, 3000).astype(np.float32)
    g[:50] = np.float32(np.pi)
    g[50:100] = np.float32(-np.pi)
    g[100:150] = (-np.pi + np.arange(50) * 2 * np.pi / 125).astype(np.float32)
    for kw in [dict(max_level=3), dict(bounds=(-1.2, -1.1, 1.3, 1.05), capacity=4100, max_level=6),
               dict(radius_s=0.002, max_level=0)]:  # 0.002: the dense cell table would be too large
        host = build_index(s, g, on_device=False, **kw)
        dev = build_index(s, g, on_device=True, **kw)
        chex.assert_trees_all_equal(host, dev)
        assert (host.n_x, host.n_y, host.n_g, host.h_x, host.max_window) == (
            dev.n_x, dev.n_y, dev.n_g, dev.h_x, dev.max_window)
    assert host.h_x > 0.25 * 0.002 * 1.001  # the last case did coarsen
    flat = np.zeros_like(s)  # one x-cell and one y-cell: no thresholds at all
    chex.assert_trees_all_equal(build_index(flat, g, on_device=False), build_index(flat, g, on_device=True))


def test_max_window_against_every_window():
    """``_max_window`` (slices of the rows' cell starts) against every window of ``w``
    consecutive x-cells of every row, cut short at the row's end, counted one by one; NumPy
    and JAX offsets, rows of one cell, windows wider than a row."""
    from lazyq_jax.neighbours.grid import _max_window

    rng = np.random.default_rng(5)
    for n_rows, n_x in [(1, 1), (3, 1), (5, 7), (40, 13), (2, 50)]:
        for w in [1, 2, 3, 7, 13, 60]:
            counts = rng.integers(0, 6, n_rows * n_x) * (rng.random(n_rows * n_x) < 0.6)
            offsets = np.concatenate([[0], np.cumsum(counts)])
            want = max(int(counts[r * n_x + i: r * n_x + min(i + w, n_x)].sum())
                       for r in range(n_rows) for i in range(n_x))
            assert int(_max_window(offsets, n_x, min(w, n_x))) == want
            assert int(_max_window(jnp.asarray(offsets.astype(np.int32)), n_x, min(w, n_x))) == want


def test_host_build_leaves_numpys_hugepage_advice_as_it_found_it(monkeypatch):
    """The host build turns NumPy's madvise(MADV_HUGEPAGE) off while it allocates (page
    compaction stalls) and restores the caller's setting, either way, also on an error."""
    from lazyq_jax.neighbours import common, grid

    if common._set_madvise_hugepage is None:
        pytest.skip("this NumPy has no _set_madvise_hugepage")
    s = np.random.default_rng(0).uniform(-1, 1, (500, 2)).astype(np.float32)
    g = np.zeros(500, np.float32)
    seen = []
    inner = grid._build_on_host

    def spy(*a, **kw):
        was = common._set_madvise_hugepage(False)  # read the setting inside the build
        seen.append(was)
        common._set_madvise_hugepage(was)
        return inner(*a, **kw)

    monkeypatch.setattr(grid, "_build_on_host", spy)
    original = common._set_madvise_hugepage(True)
    try:
        for setting in (True, False):
            common._set_madvise_hugepage(setting)
            build_index(s, g, on_device=False)
            assert common._set_madvise_hugepage(setting) == setting  # restored
        monkeypatch.setattr(grid, "_entries", lambda *a, **kw: 1 / 0)
        common._set_madvise_hugepage(True)
        with pytest.raises(ZeroDivisionError):
            build_index(s, g, on_device=False)
        assert common._set_madvise_hugepage(True) is True
    finally:
        common._set_madvise_hugepage(original)
    assert seen == [False, False, False]


@contextlib.contextmanager
def _lowerings():
    """The XLA programs lowered (to be compiled or read from a cache) inside the block."""
    seen = []

    def listen(event, duration_secs, **kwargs):
        if event == "/jax/core/compile/jaxpr_to_mlir_module_duration":
            seen.append(event)

    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        yield seen
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)


def test_bad_inputs_raise_before_anything_compiles():
    """Every shape and kind check of the public functions runs at the boundary: a bad input
    raises its error before any program is lowered (shapes unique to this test, so that a
    late check would have to compile)."""
    rng = np.random.default_rng(5)
    key = jax.random.key(0)
    s2, a, s3 = rng.uniform(-1, 1, (37, 2)), rng.uniform(-3, 3, 37), rng.uniform(-1, 1, (37, 3))
    grid = build_index(s2, a, k=3, max_level=2)
    policy = build_policy_index(s3, a, k=3, radius_s=0.3, radius_g=0.5, growth=1.5, max_level=3)
    scan = build_scan_index(s3, None, k=3)
    cases = [
        # the data of find_neighbours' cases: 29 points (not the indices' 37, which compiled)
        (lambda: find_neighbours(key, s2[:29], a[:29], s2[:7], rng.normal(size=(7, 3)), k=3), "query goals"),
        (lambda: find_neighbours(key, s2[:29], a[:29], np.full((7, 2), np.nan), a[:7], k=3), "NaN"),
        (lambda: find_neighbours(key, s3[:29], None, s2[:7], None, k=3), "d_s=2"),
        (lambda: find_neighbours(key, s2[:29], a[:29], s2[:7], a[:7], k=30), "at least k=30"),
        (lambda: search_all(grid, key, s3[:7], a[:7]), r"\[n, 2\]"),
        (lambda: query_neighbours(grid, key, s2[:7], None), r"query_g \[Q\]"),
        (lambda: query_policy(policy, key, s2[:7], a[:7]), r"\[Q, 3\]"),
        (lambda: query_policy(policy, key, s3[:7], None), "angles"),
        (lambda: query_neighbours_scan(scan, key, s3[:7], a[:7]), "no goals"),
    ]
    for call, message in cases:
        with _lowerings() as lowered, pytest.raises(ValueError, match=message):
            call()
        assert not lowered, f"{message}: {len(lowered)} programs lowered before the error"
