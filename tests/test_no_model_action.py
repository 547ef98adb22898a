"""Where the lazy model prefers no action (``neighbours.no_model_action``): no neighbourhood
within ``max_level`` growths, or every neighbour took the same action (Eq. 6's ``beta = 0``).
The zero action is then a fixed point of deterministic dynamics; ``"random"`` draws an action
of the set's boundary from ``fold_in(key, 1)`` and leaves every other step as it was."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lazyq_jax.config import ConfigError, NeighbourConfig
from lazyq_jax.local_model import boundary_action, greedy_action
from lazyq_jax.policy import LazyPolicy, lazy_policy, make_lazy_policy, policy_index
from lazyq_jax.types import Transitions

K, C = 8, 0.1
U = np.array([0.6, -0.7, 0.4], np.float32)  # the value rises along U: the greedy action is c U / |U|


def _dataset():
    """Three places in a 3-D state space without goals: around the origin many moves whose
    values rise along ``U`` (a local model with beta ~ U); around (1, 0, 0) one move repeated
    (all neighbours took the same action: beta = 0); nothing near (5, 5, 5)."""
    rng = np.random.default_rng(0)
    s_a = rng.uniform(-0.02, 0.02, (40, 3))
    a_a = rng.normal(size=(40, 3))
    a_a = C * a_a / np.linalg.norm(a_a, axis=1, keepdims=True)
    v_a = a_a @ U
    s_b = np.array([1.0, 0.0, 0.0]) + rng.uniform(-0.02, 0.02, (40, 3))
    a_b = np.tile(C * np.array([0.0, 0.0, 1.0]), (40, 1))
    v_b = rng.normal(size=40)
    s, a, v = (np.concatenate(x).astype(np.float32) for x in ((s_a, s_b), (a_a, a_b), (v_a, v_b)))
    queries = np.array([[0.0, 0.0, 0.0], [0.01, -0.01, 0.0], [1.0, 0.0, 0.0], [1.0, 0.01, 0.0],
                        [5.0, 5.0, 5.0]], np.float32)
    return s, a, v, queries


def _policy(action_set="ball", mode="zero"):
    s, a, v, queries = _dataset()
    index = policy_index(s, None, k=K, radius_s=0.05, radius_g=0.1, growth=2 ** (1 / 3), max_level=3)
    return LazyPolicy(index, jnp.asarray(a), jnp.asarray(v), jnp.float32(C), action_set,
                      no_model_action=mode), jnp.asarray(queries)


@pytest.mark.parametrize("action_set", ["ball", "box"])
def test_random_moves_only_where_the_model_prefers_no_action(action_set):
    key = jax.random.PRNGKey(3)
    zero_policy, q = _policy(action_set, "zero")
    random_policy, _ = _policy(action_set, "random")
    a0, beta0, found0 = (np.asarray(x) for x in jax.jit(lazy_policy)(zero_policy, key, q, None))
    a1, beta1, found1 = (np.asarray(x) for x in jax.jit(lazy_policy)(random_policy, key, q, None))
    # the cases: a local model (rows 0, 1), one action in the neighbourhood (2, 3), no data (4)
    np.testing.assert_array_equal(found0, [True, True, True, True, False])
    np.testing.assert_array_equal(found1, found0)  # the query keeps its key
    assert np.all(beta0[2:4] == 0) and np.all(np.abs(beta0[:2]) > 0)
    np.testing.assert_array_equal(a0[2:], 0.0)  # the paper's tie: the zero action
    # rows 0, 1: the greedy action along U, the same in both modes (same sample, same fit)
    expected = np.asarray(greedy_action(jnp.asarray(U[None]), C, action_set))[0]
    np.testing.assert_allclose(a0[:2], np.tile(expected, (2, 1)), atol=0.02 * C)
    np.testing.assert_allclose(a1[:2], a0[:2], rtol=1e-6, atol=1e-7 * C)
    # rows 2-4: drawn from fold_in(key, 1) on the boundary of the action set
    draw = np.asarray(boundary_action(jax.random.fold_in(key, 1), q.shape, C, action_set))
    np.testing.assert_allclose(a1[2:], draw[2:], rtol=1e-6)
    if action_set == "ball":
        np.testing.assert_allclose(np.linalg.norm(a1[2:], axis=1), C, rtol=1e-6)
    else:
        np.testing.assert_array_equal(np.abs(a1[2:]), np.float32(C))
    other = np.asarray(jax.jit(lazy_policy)(random_policy, jax.random.PRNGKey(4), q, None)[0])
    assert not np.allclose(other[2:], a1[2:])  # a new key, a new draw


@pytest.mark.parametrize("action_set", ["ball", "box"])
def test_boundary_actions_are_uniform(action_set):
    n = 20000
    a = np.asarray(boundary_action(jax.random.PRNGKey(0), (n, 3), C, action_set), np.float64)
    if action_set == "ball":
        np.testing.assert_allclose(np.linalg.norm(a, axis=1), C, rtol=1e-6)
        # each component of a uniform direction in 3-D has mean 0 and variance c^2 / 3
        bound = 5 * C * np.sqrt(1 / 3 / n)
    else:
        np.testing.assert_array_equal(np.abs(a), np.float32(C))
        bound = 5 * C * np.sqrt(1 / n)  # +-c with probability 1/2 each
    assert np.all(np.abs(a.mean(0)) < bound), (a.mean(0), bound)
    np.testing.assert_allclose(np.mean(a * a, 0), C ** 2 / (3 if action_set == "ball" else 1), rtol=0.05)


def test_no_model_action_is_checked():
    with pytest.raises(ConfigError, match="no_model_action"):
        NeighbourConfig(no_model_action="noise")
    s, a, v, _ = _dataset()
    data = Transitions(s=jnp.asarray(s), a=jnp.asarray(a), s_next=jnp.asarray(s + a), r=jnp.zeros(len(s)),
                       g=None, done=jnp.zeros(len(s), bool))
    with pytest.raises(ValueError, match="no_model_action"):
        make_lazy_policy(lambda x, g: jnp.zeros(x.shape[0]), data, gamma=0.9, action_length=C,
                         no_model_action="noise")


def test_the_in_sample_greedy_step_takes_the_best_neighbours_action():
    """``greedy="data"``: where the neighbourhood is the whole cluster (exactly k points near the
    origin), the step is the cluster's action of the largest ``beta . a_j``, with ``beta`` of
    NumPy's float64 least squares of ``[1, a] -> v`` (a data row, bitwise); where beta = 0 and
    where nothing is found, no action, as with ``"set"``."""
    rng = np.random.default_rng(1)
    s_a = rng.uniform(-0.02, 0.02, (K, 3))
    a_a = rng.uniform(-C, C, (K, 3))
    v_a = a_a @ U + 0.001 * rng.normal(size=K)
    s_b = np.array([1.0, 0.0, 0.0]) + rng.uniform(-0.02, 0.02, (K, 3))
    a_b = np.tile([0.0, 0.0, C], (K, 1))
    s, a, v = (np.concatenate(x).astype(np.float32) for x in ((s_a, s_b), (a_a, a_b), (v_a, rng.normal(size=K))))
    index = policy_index(s, None, k=K, radius_s=0.05, radius_g=0.1, growth=2 ** (1 / 3), max_level=3)
    policy = LazyPolicy(index, jnp.asarray(a), jnp.asarray(v), jnp.float32(C), "box", greedy="data")
    q = jnp.asarray([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [5.0, 5.0, 5.0]], jnp.float32)
    act, beta, found = (np.asarray(x) for x in jax.jit(lazy_policy)(policy, jax.random.PRNGKey(0), q, None))
    np.testing.assert_array_equal(found, [True, True, False])
    X = np.concatenate([np.ones((K, 1)), a[:K].astype(np.float64)], 1)
    beta_ref = np.linalg.lstsq(X, v[:K].astype(np.float64), rcond=None)[0][1:]
    # |beta| ~ |U| ~ 1 from actions ~ c = 0.1 and 8 rows: float32 solves agree to ~1e-4
    np.testing.assert_allclose(beta[0], beta_ref, rtol=1e-3, atol=1e-3)
    # (the best two neighbours' scores differ by 0.007, far above float32's error in them)
    np.testing.assert_array_equal(act[0], a[np.argmax(a[:K] @ beta_ref)])
    assert np.all(beta[1] == 0)
    np.testing.assert_array_equal(act[1:], 0.0)
    with pytest.raises(ConfigError, match="greedy"):
        NeighbourConfig(greedy="best")
