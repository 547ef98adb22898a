"""Jittable general-space queries (neighbours_query) against the NumPy reference, the
dispatch of find_neighbours by shape, and a 3-D task learned through the public API."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lazyq_jax as lq
from lazyq_jax.neighbours.nd import find_neighbours_nd, membership_level_reference
from lazyq_jax.neighbours.query import build_scan_index, query_neighbours_scan

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


@pytest.mark.parametrize("d_s, goal, k", [(3, "angle", 5), (1, None, 400), (4, "vector", 12), (2, "vector", 40)])
def test_scan_query_matches_the_reference(d_s, goal, k):
    rng = np.random.default_rng(d_s)
    s, g, qs, qg = _case(rng, 3000, 40, d_s, goal)
    index = build_scan_index(s, g, k=k, radius_s=RS, radius_g=RG, growth=GROWTH, max_level=MAX_LEVEL)
    nb = jax.jit(query_neighbours_scan)(index, jax.random.PRNGKey(0), qs, qg)
    lam = membership_level_reference(s, g, qs, qg, radius_s=RS, radius_g=RG, growth=GROWTH)
    ref_level = np.sort(lam, axis=1)[:, k - 1]
    level, idx, count = np.asarray(nb.level), np.asarray(nb.idx), np.asarray(nb.count)
    inside = ref_level <= MAX_LEVEL
    assert inside.any() and (ref_level > 0).any()  # the case exercises growth
    np.testing.assert_array_equal(level[inside], ref_level[inside])
    np.testing.assert_array_equal(count[inside], (lam <= ref_level[:, None]).sum(1)[inside])
    assert (level[~inside] == -1).all() and (idx[~inside] == -1).all()
    for row in np.flatnonzero(inside):
        assert len(set(idx[row])) == k  # distinct
        assert (lam[row, idx[row]] <= level[row]).all()  # members of B_level


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


def test_find_neighbours_dispatches_by_shape():
    rng = np.random.default_rng(1)
    s, g, qs, qg = _case(rng, 2000, 30, 3, "vector")
    key = jax.random.PRNGKey(5)
    a = lq.find_neighbours(key, s, g, qs, qg, k=8, radius_s=RS, radius_g=RG)
    b = find_neighbours_nd(key, s, g, qs, qg, k=8, radius_s=RS, radius_g=RG)
    for x, y in zip((a.idx, a.level, a.count), (b.idx, b.level, b.count)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    with pytest.raises(ValueError, match="mesh"):
        lq.find_neighbours(key, s, g, qs, qg, k=8, mesh=object())


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
