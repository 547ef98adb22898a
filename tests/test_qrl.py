"""Quasimetric RL (:mod:`lazyq_jax.agents.qrl`), OGBench's ``qrl`` agent.

* the interval quasimetric embedding (IQE) against a brute-force union of intervals in
  float64 (ties, nesting, empty intervals), against OGBench's own sort-based computation
  (values and gradients), and its quasimetric properties;
* every loss against an independent NumPy (float64) re-computation with tiny networks;
* which parameters each loss differentiates (OGBench's stored vs gradient parameters) and
  the dual variable's direction;
* learning on the 1-D reaching task of tests/test_gc_agents.py: the learned distance ranks
  goals by the moves they need and the actor moves towards the goal from uniformly random
  behaviour;
* config and data validation.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.stats import spearmanr
from test_gc_agents import REACH, C, f64, np_log_prob, np_mlp, np_project, reach_probes, reach_task

from lazyq_jax import agents
from lazyq_jax.agents import qrl, reference
from lazyq_jax.agents.base import Problem, Spec
from lazyq_jax.config import ConfigError
from lazyq_jax.types import Transitions

TINY = {"steps": 7, "batch_size": 16, "width": 8, "depth": 2, "blocks": 3, "latent_dim": 12,
        "components": 4}

# ----------------------------------------------------------------------------- the IQE


def union_length(x, y):
    """The length of the union of the intervals ``[x_i, y_i]`` with ``x_i < y_i``, by merging
    them in order of their starts (float64)."""
    total, lo, hi = 0.0, None, None
    for a, b in sorted((a, b) for a, b in zip(x, y) if a < b):
        if hi is None or a > hi:
            total += 0.0 if hi is None else hi - lo
            lo, hi = a, b
        else:
            hi = max(hi, b)
    return total + (0.0 if hi is None else hi - lo)


def np_components(x, y, k):
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    groups = x.shape[-1] // k
    return np.array([[union_length(x[r, i * k:(i + 1) * k], y[r, i * k:(i + 1) * k])
                      for i in range(groups)] for r in range(x.shape[0])])


def np_iqe(x, y, alpha_raw, k):
    lengths = np_components(x, y, k)
    a = 1.0 / (1.0 + np.exp(-alpha_raw))
    return a * lengths.mean(-1) + (1 - a) * lengths.max(-1)


def hard_cases():
    """Groups of 4 intervals with ties, nesting, touching, identical and empty intervals."""
    rows = [([0, 1, 2, 3], [1, 2, 3, 4]),          # touching: one interval of length 4
            ([0, 0, 0, 0], [1, 2, 3, 4]),          # equal starts, nested
            ([0, 1, 1, 5], [4, 2, 3, 6]),          # nested and disjoint
            ([2, 2, 2, 2], [3, 3, 3, 3]),          # identical
            ([1, 3, 5, 7], [0, 3, 4, 8]),          # empty (x > y, x = y) and one valid
            ([5, 4, 3, 2], [1, 1, 1, 1]),          # all empty
            ([-1, 0.5, 0.5, 2], [1, 0.5, 3, 2.5]),  # a zero-length one inside another
            ([3, 0, 2, 1], [4, 5, 2.5, 1.5])]      # unsorted starts, one covering all
    x = np.array([r[0] for r in rows], np.float32)
    y = np.array([r[1] for r in rows], np.float32)
    return x, y


def test_iqe_components_are_unions_of_intervals():
    x, y = hard_cases()
    got = np.asarray(qrl.iqe_components(jnp.asarray(x), jnp.asarray(y), 4))
    np.testing.assert_array_equal(got[:, 0], [4, 4, 5, 1, 1, 0, 4, 5])  # exact: small integers
    ogbench = np.asarray(qrl.iqe_components_sorted(jnp.asarray(x), jnp.asarray(y), 4))
    np.testing.assert_array_equal(ogbench[:, 0], got[:, 0])
    rng = np.random.default_rng(0)
    for k in (1, 3, 8):
        x = rng.normal(size=(40, 4 * k)).astype(np.float32)
        y = rng.normal(size=(40, 4 * k)).astype(np.float32)
        x[:10, 1] = x[:10, 0]  # tied starts
        got = np.asarray(qrl.iqe_components(jnp.asarray(x), jnp.asarray(y), k))
        # float32 sums of at most k lengths of O(1) numbers
        np.testing.assert_allclose(got, np_components(x, y, k), rtol=0, atol=1e-5 * k)


def test_iqe_value_and_gradient_match_ogbenchs_sort():
    """The same function as OGBench's sort-based code, so the same gradients (away from ties,
    where either is one of the one-sided derivatives)."""
    rng = np.random.default_rng(1)
    x = jnp.asarray(rng.normal(size=(64, 32)), jnp.float32)
    y = jnp.asarray(rng.normal(size=(64, 32)), jnp.float32)
    w = jnp.asarray(rng.normal(size=(64, 4)), jnp.float32)  # weights of the 4 groups
    ours = lambda x, y: jnp.sum(qrl.iqe_components(x, y, 8) * w)
    theirs = lambda x, y: jnp.sum(qrl.iqe_components_sorted(x, y, 8) * w)
    np.testing.assert_allclose(ours(x, y), theirs(x, y), rtol=1e-5)
    for got, want in zip(jax.grad(ours, (0, 1))(x, y), jax.grad(theirs, (0, 1))(x, y), strict=True):
        # each entry is a sum of +-w over at most one group: exact up to one rounding
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-6)
    assert float(jnp.sum(jax.grad(ours)(x, y) != 0)) > 100  # the gradient is exercised


def test_iqe_is_a_quasimetric():
    """``d(x, x) = 0``, ``d >= 0``, the triangle inequality, and asymmetry, for any latents."""
    rng = np.random.default_rng(2)
    x, y, z = (jnp.asarray(rng.normal(size=(500, 24)), jnp.float32) for _ in range(3))
    d = lambda a, b: np.asarray(qrl.iqe(a, b, jnp.float32(0.3), 8), np.float64)
    np.testing.assert_array_equal(d(x, x), 0.0)
    assert (d(x, y) >= 0).all()
    assert (d(x, z) <= d(x, y) + d(y, z) + 1e-5).all()  # float32 sums of O(1) lengths
    assert np.abs(d(x, y) - d(y, x)).max() > 0.1
    np.testing.assert_allclose(d(x, y), np_iqe(x, y, 0.3, 8), rtol=1e-5, atol=1e-5)


# ----------------------------------------------------------------------------- losses


def tiny(problem, seed=0, n=6, **extra):
    """``(agent, params, batch)``: tiny networks, IQE mixing weight and dual moved off their
    initial values, and a batch whose goals are states."""
    agent = qrl.make(qrl.QRLConfig(**{**TINY, **extra}), problem)
    rng = np.random.default_rng(seed)
    c = problem.action_length
    s = rng.uniform(-2, 2, (n, 2))
    a = rng.uniform(-c, c, (n, 2))
    f = lambda x: jnp.asarray(x, jnp.float32)
    b = Transitions(s=f(s), a=f(a), s_next=f(s + a), r=-jnp.ones(n), g=f(rng.uniform(-2, 2, (n, 2))),
                    done=jnp.zeros(n, bool))
    params = jax.jit(agent.init_model, static_argnums=1)(jax.random.PRNGKey(1), Spec.of(b))["params"]
    last = f"Dense_{TINY['depth'] - 1}"
    actor = jax.tree.map(lambda x: x, params["actor"])  # means outside the box: the clip is used
    actor["params"][last] = {"kernel": actor["params"][last]["kernel"] * 300.0,
                             "bias": actor["params"][last]["bias"]}
    phi = jax.tree.map(lambda x: x, params["phi"])  # latents ~10x: some transitions exceed 1
    phi["params"][last] = {"kernel": phi["params"][last]["kernel"] * 10.0,
                           "bias": phi["params"][last]["bias"]}
    params = {**params, "actor": actor, "phi": phi, "alpha_raw": jnp.float32(-0.4),
              "log_lam": jnp.float32(0.7)}
    return agent, params, b


def test_losses_match_numpy():
    problem = Problem(action_length=0.5, action_set="box", state_scale=2.0)
    agent, params, batch = tiny(problem, alpha=0.2, eps=0.01)
    cfg, c, k = agent.config, problem.action_length, agent.config.components
    p, b = f64(params), f64(batch)
    phi = lambda s: np_mlp(p["phi"], s / problem.state_scale, True)
    dyn = lambda z, a: z + np_mlp(p["dynamics"], np.concatenate([z, a / c], 1), True)
    d = lambda z, w: np_iqe(z, w, p["alpha_raw"], k)
    lam = np.exp(p["log_lam"])
    _, metrics = jax.jit(agent.loss)(params, batch)

    d_neg, d_pos = d(phi(b.s), phi(b.g)), d(phi(b.s), phi(b.s_next))
    softplus = lambda v: np.log1p(np.exp(v))
    d_neg_loss = np.mean(100 * softplus(5 - d_neg / 100))
    d_pos_loss = np.mean(np.maximum(d_pos - 1, 0) ** 2)
    assert (d_pos > 1).any()  # the constraint is active somewhere
    np.testing.assert_allclose(metrics["d_neg_loss"], d_neg_loss, rtol=1e-5)
    np.testing.assert_allclose(metrics["d_pos_loss"], d_pos_loss, rtol=1e-4, atol=1e-7)
    np.testing.assert_allclose(metrics["value_loss"], d_neg_loss + lam * d_pos_loss, rtol=1e-5)
    np.testing.assert_allclose(metrics["lam_loss"], lam * (cfg.eps - d_pos_loss), rtol=1e-4)

    z, z_next = phi(b.s), phi(b.s_next)
    pred = dyn(z, b.a)
    dyn_loss = np.mean(d(z_next, pred) + d(pred, z_next)) / 2
    np.testing.assert_allclose(metrics["dynamics_loss"], dyn_loss, rtol=1e-5)

    x = np.concatenate([b.s / problem.state_scale, b.g], 1)
    mean = c * np_mlp(p["actor"], x, False)
    a_pi = np_project(problem, mean)
    assert (np.abs(mean) > c).any() and (np.abs(mean) < c).any()  # the clip is exercised
    q = -d(dyn(z, a_pi), phi(b.g))
    q_loss = -q.mean() / (np.abs(q).mean() + 1e-6)
    bc_loss = -cfg.alpha * np.mean(np_log_prob(problem, mean, b.a))
    np.testing.assert_allclose(metrics["q_loss"], q_loss, rtol=1e-5)
    np.testing.assert_allclose(metrics["actor_loss"], q_loss + bc_loss, rtol=1e-5)


def test_each_loss_differentiates_what_ogbench_does():
    """The actor loss moves the actor only (phi, the dynamics and the IQE weight are OGBench's
    stored parameters there); the value and dynamics losses never move the actor; the dual
    grows while the transitions' loss exceeds ``eps`` and shrinks below it."""
    problem = Problem(action_length=0.5, action_set="box")
    agent, params, b = tiny(problem)
    grads = {name: jax.grad(lambda p, f=fn: f(p, b)[0])(params)
             for name, fn in (("value", agent.value_loss), ("dynamics", agent.dynamics_loss),
                              ("actor", agent.actor_loss))}
    nonzero = lambda tree: any(bool(jnp.any(x != 0)) for x in jax.tree.leaves(tree))
    assert [k for k in params if nonzero(grads["actor"][k])] == ["actor"]
    assert {k for k in params if nonzero(grads["value"][k])} == {"phi", "alpha_raw", "log_lam"}
    assert {k for k in params if nonzero(grads["dynamics"][k])} == {"phi", "alpha_raw", "dynamics"}
    d_pos_loss = float(agent.value_loss(params, b)[1]["d_pos_loss"])
    for eps in (0.5 * d_pos_loss, 2.0 * d_pos_loss):
        a = qrl.make(dataclasses.replace(agent.config, eps=eps), problem)
        g = float(jax.grad(lambda p, a=a: a.value_loss(p, b)[0])(params)["log_lam"])
        np.testing.assert_allclose(g, np.exp(0.7) * (eps - d_pos_loss), rtol=1e-5)


def test_value_fn_is_minus_the_distance():
    problem = Problem(action_length=0.5, action_set="box", state_scale=2.0)
    agent, _, b = tiny(problem)
    state = agent.init(jax.random.PRNGKey(3), b)
    p = f64(state.model["params"])
    phi = lambda s: np_mlp(p["phi"], s / 2.0, True)
    want = -np_iqe(phi(np.asarray(b.s, np.float64)), phi(np.asarray(b.g, np.float64)),
                   p["alpha_raw"], agent.config.components)
    np.testing.assert_allclose(agent.value_fn(state)(b.s, b.g), want, rtol=1e-5, atol=1e-6)


# ----------------------------------------------------------------------------- learning

# Measured over 4 seeds (key, data), 500 steps: sign agreement with the optimal move 1.00,
# mean a . sign(g - s) / c 0.85-0.99, Spearman(-d, moves needed) 0.86-0.90.
LEARN = {"batch_size": 256, "width": 32, "depth": 2, "blocks": 1, "learning_rate": 1e-3,
         "steps": 500, "latent_dim": 32}


def test_qrl_learns_distances_and_moves_towards_the_goal():
    """The rows' own goals are states (the reaching task's goals): ``d`` ranks them by the
    moves they need, and the actor, trained by DDPG+BC through the latent dynamics on
    uniformly random moves, moves towards the goal."""
    agent = qrl.make(qrl.QRLConfig(**LEARN), REACH)
    data = reach_task(1, 4000)
    state, metrics = jax.jit(agent.train)(jax.random.PRNGKey(0), data)
    assert all(np.all(np.isfinite(np.asarray(v))) for v in jax.tree.leaves(metrics))
    s, g, sign = reach_probes()
    actions = np.asarray(agent.policy(state)(None, s, g))[:, 0]
    assert np.all(np.abs(actions) <= C)
    assert np.mean(np.sign(actions) == sign) >= 0.9
    assert np.mean(actions * sign) > 0.5 * C
    moves = np.abs(np.asarray(g - s))[:, 0] / C
    assert spearmanr(-np.asarray(agent.value_fn(state)(s, g)), moves)[0] > 0.75  # d vs moves
    # the transitions' constraint holds on average (the dual's margin eps = 0.05)
    assert float(metrics["d_pos_mean"][-1]) < 1.2


# ----------------------------------------------------------------------------- configs and data


def test_defaults_are_ogbenchs():
    cfg = qrl.QRLConfig()
    assert (cfg.learning_rate, cfg.batch_size, cfg.width, cfg.depth, cfg.latent_dim,
            cfg.components, cfg.eps, cfg.alpha, cfg.layer_norm) == (
        3e-4, 1024, 512, 4, 512, 8, 0.05, 0.0003, True)
    assert agents.config_class("qrl") is qrl.QRLConfig and "qrl" in agents.BASELINES


@pytest.mark.parametrize("field, value, match", [
    ("latent_dim", 12, "multiple of components"), ("components", 0, "components must be"),
    ("eps", 0.0, "eps must be"), ("alpha", -1.0, "alpha must be"),
    ("layer_norm", "yes", "layer_norm must be"), ("goals", "future", "goals must be")])
def test_config_errors(field, value, match):
    with pytest.raises(ConfigError, match=match):
        qrl.QRLConfig(**{field: value})


def test_value_goals_are_random_states_and_actor_goals_later_ones():
    """OGBench's QRL goals from trajectories: value goals uniform over all rows, actor goals a
    later state of the row's own trajectory."""
    n_traj, length = 50, 40
    n = n_traj * length
    idx = np.arange(n)
    s = np.stack([idx, idx // length], -1).astype(np.float32)
    data = Transitions(s=jnp.asarray(s), a=jnp.zeros((n, 2)), s_next=jnp.asarray(s + 1),
                       r=-jnp.ones(n), g=jnp.asarray(s), done=jnp.zeros(n, bool),
                       traj_last=jnp.asarray((idx // length + 1) * length - 1, jnp.int32))
    agent = qrl.make(qrl.QRLConfig(**TINY), Problem(action_length=1.0, action_set="box"))
    rows = jax.random.randint(jax.random.PRNGKey(0), (100_000,), 0, n)
    value, actor = agent.batch(data, rows, jax.random.PRNGKey(1), jnp.int32(n))
    g_v, g_a = (np.asarray(x[:, 0]).astype(int) for x in (value.g, actor.g))
    r = np.asarray(rows)
    # uniform over the rows: each tenth of them holds 1/10 of the goals (5 sigma of 100,000)
    counts = np.bincount(g_v * 10 // n, minlength=10) / len(g_v)
    np.testing.assert_allclose(counts, 0.1, atol=5 * np.sqrt(0.09 / len(g_v)))
    same = (g_v // length) == (r // length)
    assert abs(same.mean() - 1 / n_traj) < 5 * np.sqrt(0.02 / len(g_v))
    assert ((g_a // length) == (r // length)).all() and (g_a >= r).all()


@pytest.mark.parametrize("goal", ["angle", None, 3])
def test_goals_must_be_states(goal):
    data = reference.line_task(0, 16, 2, goal if goal != 3 else "vector")
    if goal == 3:
        data = data.replace(g=jnp.zeros((16, 3)))
    agent = qrl.make(qrl.QRLConfig(**TINY), Problem(action_length=0.1, action_set="box"))
    with pytest.raises(ValueError, match="goals must be states"):
        agent.init(jax.random.PRNGKey(0), data)
