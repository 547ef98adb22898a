"""Lazy Q with a goal feature map (``Problem.goal_features``): goals too wide for a neighbour
search (OGBench's 28-D goal observations) are compared through ``psi(g)``, in training's
neighbourhoods and in the policy's queries, while the networks see the whole goal.

References: the brute-force membership levels of the mapped points; the same search run on
goals mapped beforehand (the same compiled search on the same inputs: bitwise)."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from lazyq_jax.agents import lazy
from lazyq_jax.agents.base import Problem, stack_trees
from lazyq_jax.config import NeighbourConfig, TrainConfig
from lazyq_jax.neighbours.nd import membership_level_reference
from lazyq_jax.parallel import over_seeds
from lazyq_jax.policy import lazy_policy
from lazyq_jax.types import Transitions

N, D_S, D_G, K = 400, 3, 6, 8
NC = NeighbourConfig(k=K, radius_s=0.3, radius_g=0.4)
TC = TrainConfig(cycles=1, epochs=1, batch_size=128, width=8, depth=2)


def psi(g):
    """What 'success reads' of the test's goals: their first two coordinates, scaled."""
    return 2.0 * g[..., :2]


def data(seed: int) -> Transitions:
    rng = np.random.default_rng(seed)
    s = rng.uniform(-1, 1, (N, D_S)).astype(np.float32)
    g = rng.uniform(-1, 1, (N, D_G)).astype(np.float32)  # coordinates 2: are noise to psi
    a = rng.uniform(-1, 1, (N, 2)).astype(np.float32)
    return Transitions(s=jnp.asarray(s), a=jnp.asarray(a), s_next=jnp.asarray(s + 0.1 * a[:, :1]),
                       r=-jnp.ones(N), g=jnp.asarray(g), done=jnp.zeros(N, bool))


def agent(goal_features=None):
    problem = Problem(action_length=1.0, action_set="box", goal_features=goal_features)
    return lazy.make(lazy.LazyConfig(train=TC, neighbours=NC), problem)


def test_neighbourhoods_are_those_of_the_mapped_goals():
    """The training neighbourhoods with ``psi`` hold the brute-force k-th membership level of
    the points ``(s, psi(g))`` and only members; they equal the ones found on ``psi(g)`` given
    as the data's goals, bitwise; without ``psi`` the 6-D goals give other neighbourhoods."""
    d = data(0)
    nb = agent(psi).prepare(0, d, N, 0)
    g2 = np.asarray(psi(np.asarray(d.g)))
    lam = membership_level_reference(np.asarray(d.s), g2, np.asarray(d.s), g2,
                                     radius_s=NC.radius_s, radius_g=NC.radius_g)
    level = np.sort(lam, axis=1)[:, K - 1]
    np.testing.assert_array_equal(np.asarray(nb.level), level)
    assert np.all(np.take_along_axis(lam, np.asarray(nb.idx), axis=1) <= level[:, None])
    mapped = agent().prepare(0, d.replace(g=jnp.asarray(g2)), N, 0)
    np.testing.assert_array_equal(np.asarray(nb.idx), np.asarray(mapped.idx))
    raw = agent().prepare(0, d, N, 0)
    assert not np.array_equal(np.asarray(raw.level), np.asarray(nb.level))


def test_the_policy_queries_with_the_mapped_goal():
    """Two seeds' policies: the index is the one built on the mapped goals (bitwise), and an
    act with 6-D query goals equals the same policy queried with ``psi(g)`` directly (beta up
    to float32 rounding of the same fit: the neighbours are the same rows)."""
    ds = [data(0), data(1)]
    stacked, n_valid = stack_trees(ds), np.array([N, N], np.int32)
    a = agent(psi)
    keys = jnp.stack([jax.random.PRNGKey(0), jax.random.PRNGKey(1)])
    states = over_seeds(a.init, 2)(keys, stacked)
    policy = a.policies(states, stacked, n_valid)
    assert policy.goal_features is psi
    mapped = stack_trees([d.replace(g=psi(d.g)) for d in ds])
    ref_index = agent().policies(over_seeds(agent().init, 2)(keys, mapped), mapped, n_valid).index
    jax.tree.map(np.testing.assert_array_equal, policy.index, ref_index)

    rng = np.random.default_rng(2)
    s = jnp.asarray(rng.uniform(-0.9, 0.9, (2, 32, D_S)), jnp.float32)
    g = jnp.asarray(rng.uniform(-0.9, 0.9, (2, 32, D_G)), jnp.float32)
    plain = dataclasses.replace(policy, goal_features=None)
    act = jax.vmap(lambda p, k, s_, g_: lazy_policy(p, k, s_, g_))
    _, beta, found = act(policy, keys, s, g)
    _, beta_ref, found_ref = act(plain, keys, s, psi(g))
    np.testing.assert_array_equal(np.asarray(found), np.asarray(found_ref))
    assert np.mean(np.asarray(found)) > 0.9
    # |beta| ~ |V| / |a| ~ 1: float32 rounding of the same least squares, a few ulps of it
    np.testing.assert_allclose(np.asarray(beta), np.asarray(beta_ref), rtol=1e-4, atol=1e-5)
