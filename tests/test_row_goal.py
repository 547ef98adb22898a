"""``train.bootstrap_goal="row"``: a neighbour's next state valued at the row's goal with the
row's reward, ``y_ij = r_i + gamma (1 - done_i) V(s'_j, g_i)`` (targets), and at the query's
goal in the policy; against NumPy least squares and the exact Bellman backup of a value that
is linear in the state."""

from __future__ import annotations


import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import pointmaze_round_trip

from lazyq_jax import agents, tasks
from lazyq_jax.agents.base import Problem
from lazyq_jax.config import ConfigError, NeighbourConfig, TrainConfig, override
from lazyq_jax.local_model import RIDGE
from lazyq_jax.neighbours.query import query_policy
from lazyq_jax.policy import LazyPolicy, lazy_policy, policy_index
from lazyq_jax.targets import lazy_target, local_fits
from lazyq_jax.train import make_train
from lazyq_jax.types import Transitions

GAMMA, STEP = 0.9, 0.2
W = np.array([0.7, -1.3], np.float32)  # V(s, g) = W . (s - g) + b(g): linear in the state


def value(s, g):
    return (s - g) @ W + 0.5 * jnp.sum(g, axis=-1)


def _data(n=40, k=10, seed=0):
    """``n`` transitions of ``s' = s + STEP a`` with box actions, vector goals, some rows at
    their goal (done, reward 0); each row's neighbourhood: ``k`` random rows (any, as
    ``local_fits`` takes them)."""
    rng = np.random.default_rng(seed)
    s = rng.uniform(-1, 1, (n, 2)).astype(np.float32)
    a = rng.uniform(-1, 1, (n, 2)).astype(np.float32)
    g = rng.uniform(-1, 1, (n, 2)).astype(np.float32)
    done = rng.uniform(size=n) < 0.2
    r = np.where(done, 0.0, -1.0).astype(np.float32)
    data = Transitions(s=jnp.asarray(s), a=jnp.asarray(a), r=jnp.asarray(r), s_next=jnp.asarray(s + STEP * a),
                       g=jnp.asarray(g), done=jnp.asarray(done))
    idx = np.stack([rng.choice(n, k, replace=False) for _ in range(n)]).astype(np.int32)
    return data, idx


@pytest.mark.parametrize("batch_size", [65536, 25])  # one chunk; chunks of 25 // 10 = 2 rows
def test_row_goal_fits_equal_numpy_least_squares(batch_size):
    data, idx = _data()
    alpha, beta, y_nb = local_fits(value, data, jnp.asarray(idx), gamma=GAMMA, state_offsets=True,
                                   row_goal=True, batch_size=batch_size)
    s, a, s2, g, r, done = (np.asarray(x, np.float64) for x in (data.s, data.a, data.s_next, data.g,
                                                                data.r, data.done))
    for i in range(len(idx)):
        nb = idx[i]
        v = (s2[nb] - g[i]) @ W + 0.5 * g[i].sum()  # V(s'_j, g_i): the row's goal
        y = r[i] + GAMMA * (1 - done[i]) * v
        np.testing.assert_allclose(np.asarray(y_nb[i]), y, rtol=1e-5, atol=1e-5)
        x = np.concatenate([np.ones((len(nb), 1)), a[nb], s[nb] - s[i]], axis=1)
        coef = np.linalg.lstsq(x, y, rcond=None)[0]
        # float32 normal equations of the centred covariates: error ~ eps cond^2 |y|, plus
        # the fit's relative ridge (RIDGE = 1e-5) times |coef|
        xc = x[:, 1:] - x[:, 1:].mean(0)
        tol = 10 * (np.finfo(np.float32).eps * np.linalg.cond(xc) ** 2 + RIDGE) * (1 + np.abs(y).max())
        np.testing.assert_allclose(np.asarray(alpha[i]), coef[0], atol=tol)
        np.testing.assert_allclose(np.asarray(beta[i]), coef[1:3], atol=tol)


def test_row_goal_target_is_the_exact_backup_of_a_linear_value():
    """``V`` linear in the state: ``y_j`` is linear in ``(a_j, s_j - s_i)``, the fit exact, and
    Eq. (7)'s maximum over the box is the true Bellman backup
    ``r + gamma max_{|a_i| <= 1} V(s + STEP a, g)`` (a closed form here); the neighbours'
    own goals (another value) do not enter."""
    data, idx = _data()
    alpha, beta, y_nb = local_fits(value, data, jnp.asarray(idx), gamma=GAMMA, state_offsets=True,
                                   row_goal=True)
    target, _ = lazy_target(alpha, beta, y_nb, 1.0, clip=False, action_set="box")
    s, g, r, done = (np.asarray(x, np.float64) for x in (data.s, data.g, data.r, data.done))
    best = (s - g) @ W + 0.5 * g.sum(1) + STEP * np.abs(W).sum()  # max_a V(s + STEP a, g)
    a = np.asarray(data.a, np.float64)
    cond = max(np.linalg.cond(np.concatenate([a[nb], s[nb]], 1) - np.concatenate([a[nb], s[nb]], 1).mean(0))
               for nb in idx)  # of the centred covariates, as in the fit's normal equations
    tol = 10 * (np.finfo(np.float32).eps * cond ** 2 + RIDGE) * (1 + np.abs(np.asarray(y_nb)).max())
    np.testing.assert_allclose(np.asarray(target), r + GAMMA * (1 - done) * best, atol=tol)
    # the paper's table instead reads every neighbour at its own goal: another number
    a2, b2, _ = local_fits(value, data, jnp.asarray(idx), gamma=GAMMA, state_offsets=True)
    other, _ = lazy_target(a2, b2, y_nb, 1.0, clip=False, action_set="box")
    assert np.max(np.abs(np.asarray(other) - np.asarray(target))) > 0.1


def test_the_policy_values_neighbours_at_the_query_goal():
    """``lazy_policy`` with ``value_apply``: ``beta`` of the fit of ``V(s'_j, g)`` (the query's
    goal) over the query's state-space neighbourhood, as NumPy's least squares."""
    data, _ = _data(n=200, seed=1)
    s = np.asarray(data.s)
    index = policy_index(s, None, k=8, radius_s=0.3, radius_g=1.0, growth=2 ** (1 / 3), max_level=4)
    policy = LazyPolicy(index, data.a, jnp.zeros(200), jnp.float32(1.0), "box", states=data.s,
                        next_states=data.s_next, value_vars={}, value_apply=lambda _, s2, g: value(s2, g))
    key = jax.random.PRNGKey(2)
    q = jnp.asarray([[0.1, 0.2], [-0.5, 0.4], [0.8, -0.8]], jnp.float32)
    goals = jnp.asarray([[0.9, 0.9], [-0.9, 0.0], [0.0, 0.5]], jnp.float32)
    action, beta, found = jax.jit(lazy_policy)(policy, key, q, goals)
    nb = query_policy(index, key, q, None)
    assert bool(np.all(found))
    s2, a = np.asarray(data.s_next, np.float64), np.asarray(data.a, np.float64)
    for b in range(3):
        rows = np.asarray(nb.idx[b])
        y = (s2[rows] - np.asarray(goals[b])) @ W + 0.5 * float(goals[b].sum())
        x = np.concatenate([np.ones((len(rows), 1)), a[rows], s[rows] - np.asarray(q[b])], axis=1)
        coef = np.linalg.lstsq(x, y, rcond=None)[0]
        xc = x[:, 1:] - x[:, 1:].mean(0)
        tol = 10 * (np.finfo(np.float32).eps * np.linalg.cond(xc) ** 2 + RIDGE) * (1 + np.abs(y).max())
        np.testing.assert_allclose(np.asarray(beta[b]), coef[1:3], atol=tol)
        np.testing.assert_allclose(np.asarray(action[b]), np.sign(STEP * W), atol=1e-6)  # c sign(beta)


def test_row_goal_is_refused_where_it_is_not_exact():
    push = Problem(action_length=0.1)  # the push's reward depends on the disk's motion
    cfg = agents.LazyConfig(train=TrainConfig(bootstrap_goal="row"),
                            neighbours=NeighbourConfig(local_model="action+state"))
    with pytest.raises(ConfigError, match="state_goal_reward"):
        agents.make("lazy", cfg, problem=push)
    maze = Problem(action_length=1.0, action_set="box", state_goal_reward=True)
    agents.make("lazy", cfg, problem=maze)
    goal_offsets = agents.LazyConfig(train=TrainConfig(bootstrap_goal="row"),
                                     neighbours=NeighbourConfig(local_model="action+state+goal"))
    with pytest.raises(ConfigError, match="no goal offsets"):
        agents.make("lazy", goal_offsets, problem=maze)
    with pytest.raises(ValueError, match="no goal offsets"):
        make_train(TrainConfig(bootstrap_goal="row"), 1.0, state_offsets=True, goal_offsets=True)
    with pytest.raises(ConfigError, match="bootstrap_goal"):
        TrainConfig(bootstrap_goal="query")


def test_row_goal_through_the_cli(tmp_path):
    """The whole task at smoke scale with row goals (and one-step targets, which row goals
    need: the maze's default takes 10): trained, evaluated, reloaded, acting."""
    pointmaze_round_trip(tmp_path / "row", "train.bootstrap_goal=row", "train.target_steps=1",
                         "neighbours.local_model=action+state")
    cfg = override(tasks.preset("pointmaze", "smoke"), ["train.bootstrap_goal=row"])
    assert cfg.train.bootstrap_goal == "row"
