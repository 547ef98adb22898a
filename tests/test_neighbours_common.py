"""The shared core of the neighbour engines (lazyq_jax.neighbours.common) against NumPy."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lazyq_jax.neighbours.common import _cumsum_small, _floyd_ranks, _sample_members, _steps, stable_order


@pytest.mark.parametrize("lo, hi", [(0, 5), (0, 65_535), (0, 65_536), (-70_000, 70_000), (0, 2**40)])
@pytest.mark.parametrize("n", [0, 1, 9, 5_000])
def test_stable_order_is_numpy_stable_argsort(lo, hi, n):
    key = np.random.default_rng(n + hi % 97).integers(lo, hi, n)
    np.testing.assert_array_equal(stable_order(key), np.argsort(key, kind="stable"))


@pytest.mark.parametrize("hi", [1, 5, 65_536])
def test_stable_order_with_a_known_bound_is_numpy_stable_argsort(hi):
    key = np.random.default_rng(hi).integers(0, hi, 5_000).astype(np.int32)
    np.testing.assert_array_equal(stable_order(key, upper=hi), np.argsort(key, kind="stable"))


@pytest.mark.parametrize("n", [1, 256, 257, 100_003])
def test_cumsum_small_is_exact_up_to_its_bound(n):
    rng = np.random.default_rng(n)
    x = rng.integers(0, 33, n).astype(np.int32)  # popcounts, the use
    x[:1000] = rng.integers(0, 2**18, min(n, 1000))  # partial sums near 2**24 within a block
    x[:300] = 2**18 - 1  # the largest (the total stays within int32)
    np.testing.assert_array_equal(np.asarray(jax.jit(_cumsum_small)(jnp.asarray(x))), np.cumsum(x, dtype=np.int64))


@pytest.mark.parametrize("max_items", [1, 3, 16, 32, 90])  # the window count (<= 32) and the binary search
def test_sample_members_maps_ranks_to_the_members_in_order(max_items):
    """Rank r of a query is its r-th member in item order (bit order within an item), with
    empty items and zero words anywhere; both lookups (window count, binary search) agree with
    a NumPy walk over the members."""
    rng = np.random.default_rng(max_items)
    q, k = 300, 5
    n_q = rng.integers(1, max_items + 1, q)
    words = rng.integers(0, 2**32, n_q.sum(), dtype=np.uint64).astype(np.uint32)
    words[rng.random(words.shape) < 0.3] = 0  # empty items
    words[rng.random(words.shape) < 0.2] &= np.uint32(0x00F0000F)  # sparse ones
    first = np.concatenate([[0], np.cumsum(n_q)[:-1]])
    item_q = np.repeat(np.arange(q), n_q)
    item_start = 1000 * np.arange(words.size)  # entry of bit w of item t: 1000 t + w
    m = np.array([sum(bin(int(w)).count("1") for w in words[f:f + c]) for f, c in zip(first, n_q)])
    found = m >= k
    seed = jnp.asarray(rng.integers(0, 2**32, q, dtype=np.uint64).astype(np.uint32))
    orig = np.arange(1000 * words.size + 32, dtype=np.int32)
    args = (jnp.asarray(orig), jnp.asarray(words)[:, None], jnp.zeros(q, jnp.int32), jnp.asarray(found),
            jnp.asarray(m, jnp.int32), seed, jnp.asarray(item_q, jnp.int32), jnp.asarray(item_start, jnp.int32),
            jnp.asarray(first, jnp.int32), jnp.asarray(n_q, jnp.int32))
    ranks = np.asarray(_floyd_ranks(seed, jnp.where(jnp.asarray(found), jnp.asarray(m, jnp.int32), k), k))
    expected = np.full((q, k), -1)
    for i in np.flatnonzero(found):
        members = [1000 * t + b for t in range(first[i], first[i] + n_q[i]) for b in range(32) if words[t] >> b & 1]
        expected[i] = np.asarray(members)[ranks[i]]
    for steps in {_steps(n_q.max()), 8}:
        got = jax.jit(lambda *a, steps=steps: _sample_members(*a, k=k, steps=steps))(*args)
        np.testing.assert_array_equal(np.asarray(got), expected)
    assert found.sum() > q // 2


def test_floyd_programs_agree_and_draw_distinct_ranks(monkeypatch):
    """The unrolled program (large batches) and the loop draw the same ranks: distinct, in [0, m)."""
    from lazyq_jax.neighbours import common

    rng = np.random.default_rng(3)
    q, k = 2000, 20
    seed = jnp.asarray(rng.integers(0, 2**32, q, dtype=np.uint64).astype(np.uint32))
    m = jnp.asarray(rng.integers(k, 60, q).astype(np.int32))
    monkeypatch.setattr(common, "_UNROLL_QUERIES", 1 << 30)
    loop = np.asarray(jax.jit(lambda s, m: common._floyd_ranks(s, m, k))(seed, m))
    monkeypatch.setattr(common, "_UNROLL_QUERIES", 1)
    unrolled = np.asarray(jax.jit(lambda s, m: common._floyd_ranks(s, m, k))(seed, m))
    np.testing.assert_array_equal(loop, unrolled)
    assert ((loop >= 0) & (loop < np.asarray(m)[:, None])).all()
    assert all(len(set(r)) == k for r in loop.tolist())
