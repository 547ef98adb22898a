"""Contrastive RL (:mod:`lazyq_jax.agents.crl`), OGBench's ``crl`` agent.

* both losses against an independent NumPy (float64) re-computation with tiny networks (the
  binary NCE written out row by row, the bilinear critics, DDPG+BC through the clip);
* which parameters each loss differentiates (OGBench's stored critic in the actor's loss);
* the goals: the critic's a later state of the row's own trajectory at a geometric offset
  (mean ``1 / (1 - gamma)`` where the trajectory is long enough), the actor's a uniform one;
* learning on random walks along a line: the critic tells a row's future states from other
  rows', and the actor, trained on uniformly random moves, moves towards the goal;
* config and data validation.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_gc_agents import REACH, C, f64, member, np_log_prob, np_mlp, np_project, reach_probes

from lazyq_jax import agents
from lazyq_jax.agents import crl, reference
from lazyq_jax.agents.base import Problem, Spec
from lazyq_jax.config import ConfigError
from lazyq_jax.types import Transitions

TINY = {"steps": 7, "batch_size": 16, "width": 8, "depth": 2, "blocks": 3, "latent_dim": 6}


def tiny(problem, seed=0, n=6, **extra):
    """``(agent, params, batch)``: tiny networks, the actor's head scaled so that some means
    leave the box (the clip is exercised), a batch whose goals are states."""
    agent = crl.make(crl.CRLConfig(**{**TINY, **extra}), problem)
    rng = np.random.default_rng(seed)
    c = problem.action_length
    s = rng.uniform(-2, 2, (n, 2))
    a = rng.uniform(-c, c, (n, 2))
    f = lambda x: jnp.asarray(x, jnp.float32)
    b = Transitions(s=f(s), a=f(a), s_next=f(s + a), r=-jnp.ones(n), g=f(rng.uniform(-2, 2, (n, 2))),
                    done=jnp.zeros(n, bool))
    params = jax.jit(agent.init_model, static_argnums=1)(jax.random.PRNGKey(1), Spec.of(b))["params"]
    last = f"Dense_{TINY['depth'] - 1}"
    actor = jax.tree.map(lambda x: x, params["actor"])
    actor["params"][last] = {"kernel": actor["params"][last]["kernel"] * 300.0,
                             "bias": actor["params"][last]["bias"]}
    return agent, {**params, "actor": actor}, b


def np_bilinear(p, s, a, g, problem, latent):
    """``[2, B_s, B_g]``: ``phi_e(s_i, a_i) . psi_e(g_j) / sqrt(latent)`` for both members."""
    x = np.concatenate([s / problem.state_scale, a / problem.action_length], 1)
    return np.stack([np_mlp(member(p["phi"], e), x, True) @ np_mlp(member(p["psi"], e),
                                                                 g / problem.state_scale, True).T
                     for e in range(2)]) / np.sqrt(latent)


def test_losses_match_numpy():
    problem = Problem(action_length=0.5, action_set="box", state_scale=2.0)
    agent, params, batch = tiny(problem, alpha=0.2)
    cfg, c = agent.config, problem.action_length
    p, b = f64(params), f64(batch)
    _, metrics = jax.jit(agent.loss)(params, batch)

    logits = np_bilinear(p, b.s, b.a, b.g, problem, cfg.latent_dim)
    n = len(b.s)
    # binary cross-entropy of sigmoid(l) against 1[i = j], one term at a time
    bce = [np.log1p(np.exp(-logits[e, i, j])) if i == j else np.log1p(np.exp(logits[e, i, j]))
           for e in range(2) for i in range(n) for j in range(n)]
    np.testing.assert_allclose(metrics["contrastive_loss"], np.mean(bce), rtol=1e-5)
    mean_logits = logits.mean(0)
    np.testing.assert_allclose(metrics["logits_pos"], np.trace(mean_logits) / n, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(metrics["logits_neg"], (mean_logits.sum() - np.trace(mean_logits)) / (n * n - n),
                               rtol=1e-5, atol=1e-6)

    x = np.concatenate([b.s / problem.state_scale, b.g], 1)
    mean = c * np_mlp(p["actor"], x, False)
    a_pi = np_project(problem, mean)
    assert (np.abs(mean) > c).any() and (np.abs(mean) < c).any()  # the clip is exercised
    q = np.stack([np.diag(m) for m in np_bilinear(p, b.s, a_pi, b.g, problem, cfg.latent_dim)]).min(0)
    q_loss = -q.mean() / (np.abs(q).mean() + 1e-6)
    bc_loss = -cfg.alpha * np.mean(np_log_prob(problem, mean, b.a))
    np.testing.assert_allclose(metrics["q_loss"], q_loss, rtol=1e-5)
    np.testing.assert_allclose(metrics["bc_loss"], bc_loss, rtol=1e-5)
    np.testing.assert_allclose(metrics["actor_loss"], q_loss + bc_loss, rtol=1e-5)
    # the critic at the batch's own pairs is the diagonal of the logits
    np.testing.assert_allclose(agent.critic(params, batch.s, batch.g, batch.a),
                               np.stack([np.diag(m) for m in logits]), rtol=1e-5, atol=1e-6)


def test_each_loss_differentiates_what_ogbench_does():
    """The contrastive loss moves ``phi`` and ``psi`` only; the actor's loss the actor only
    (the critics are OGBench's stored parameters there)."""
    agent, params, b = tiny(Problem(action_length=0.5, action_set="box"))
    nonzero = lambda tree: any(bool(jnp.any(x != 0)) for x in jax.tree.leaves(tree))
    critic = jax.grad(lambda p: agent.contrastive_loss(p, b)[0])(params)
    actor = jax.grad(lambda p: agent.actor_loss(p, b)[0])(params)
    assert {k for k in params if nonzero(critic[k])} == {"phi", "psi"}
    assert {k for k in params if nonzero(actor[k])} == {"actor"}


def test_critic_goals_are_geometric_later_states_and_actor_goals_uniform_ones():
    """OGBench's CRL goals from trajectories: the critic's never the row itself (except at a
    trajectory's last row) nor another trajectory's, at a geometric offset clipped to the
    trajectory's end; the actor's a later state of the same trajectory."""
    n_traj, length = 20, 400
    n = n_traj * length
    idx = np.arange(n)
    s = np.stack([idx, idx // length], -1).astype(np.float32)
    data = Transitions(s=jnp.asarray(s), a=jnp.zeros((n, 2)), s_next=jnp.asarray(s + 1),
                       r=-jnp.ones(n), g=jnp.asarray(s), done=jnp.zeros(n, bool),
                       traj_last=jnp.asarray((idx // length + 1) * length - 1, jnp.int32))
    gamma = 0.9
    agent = crl.make(crl.CRLConfig(**TINY, gamma=gamma), Problem(action_length=1.0, action_set="box"))
    rows = jax.random.randint(jax.random.PRNGKey(0), (100_000,), 0, n)
    value, actor = agent.batch(data, rows, jax.random.PRNGKey(1), jnp.int32(n))
    g_v, g_a = (np.asarray(x[:, 0]).astype(int) for x in (value.g, actor.g))
    r = np.asarray(rows)
    last = (r // length + 1) * length - 1
    assert ((g_v // length) == (r // length)).all() and ((g_a // length) == (r // length)).all()
    assert (g_v >= np.minimum(r + 1, last)).all() and (g_a >= r).all()
    # offsets Geom(1 - gamma) on rows at least 100 from their end (the clip at 1e-4): mean 1 / (1 - gamma)
    far = last - r >= 100
    offsets = (g_v - r)[far]
    np.testing.assert_allclose(offsets.mean(), 1 / (1 - gamma), rtol=5 * np.sqrt(gamma) / np.sqrt(far.sum()))
    np.testing.assert_allclose((offsets == 1).mean(), 1 - gamma, atol=5 * np.sqrt(0.09 / far.sum()))


def walks(seed, n_traj=100, length=40):
    """Random walks on [-1, 1]: uniform moves in [-C, C], clipped to the line."""
    rng = np.random.default_rng(seed)
    a = rng.uniform(-C, C, (n_traj, length, 1))
    s = np.empty((n_traj, length, 1))
    cur = rng.uniform(-1, 1, (n_traj, 1))
    for t in range(length):
        s[:, t], cur = cur, np.clip(cur + a[:, t], -1, 1)
    s_next = np.concatenate([s[:, 1:], cur[:, None]], 1)
    n = n_traj * length
    f = lambda x: jnp.asarray(x.reshape(n, -1), jnp.float32)
    return Transitions(s=f(s), a=f(a), s_next=f(s_next), r=-jnp.ones(n), g=f(s),
                       done=jnp.zeros(n, bool),
                       traj_last=jnp.asarray((np.arange(n) // length + 1) * length - 1, jnp.int32))


# Measured over 4 seeds (key and data), 3,000 steps: sign agreement with the optimal move 1.00,
# mean a . sign(g - s) / c 0.95-0.97, logits of positives -4.5 against -8.4 to -8.6 of negatives
# (2,000 steps of one hidden layer: one seed of four at 0.48 sign agreement).
LEARN = {"batch_size": 256, "width": 32, "depth": 3, "blocks": 1, "learning_rate": 1e-3,
         "steps": 3000, "latent_dim": 32, "gamma": 0.9, "goals": "trajectories"}


def test_crl_tells_future_states_and_moves_towards_the_goal():
    """Trained on uniformly random walks, with a row's later states as its positives: the
    positives' logits exceed the negatives', and the DDPG+BC actor moves towards the goal."""
    agent = crl.make(crl.CRLConfig(**LEARN), REACH)
    state, metrics = jax.jit(agent.train)(jax.random.PRNGKey(0), walks(0))
    assert all(np.all(np.isfinite(np.asarray(v))) for v in jax.tree.leaves(metrics))
    assert float(metrics["logits_pos"][-1]) > float(metrics["logits_neg"][-1]) + 2.0
    s, g, sign = reach_probes()
    actions = np.asarray(agent.policy(state)(None, s, g))[:, 0]
    assert np.all(np.abs(actions) <= C)
    assert np.mean(np.sign(actions) == sign) >= 0.9
    assert np.mean(actions * sign) > 0.5 * C


def test_defaults_are_ogbenchs():
    cfg = crl.CRLConfig()
    assert (cfg.learning_rate, cfg.batch_size, cfg.width, cfg.depth, cfg.latent_dim, cfg.alpha,
            cfg.layer_norm, cfg.gamma) == (3e-4, 1024, 512, 4, 512, 0.03, True, 0.99)
    assert agents.config_class("crl") is crl.CRLConfig and "crl" in agents.BASELINES


@pytest.mark.parametrize("field, value, match", [
    ("latent_dim", 0, "latent_dim must be"), ("alpha", -1.0, "alpha must be"),
    ("layer_norm", "yes", "layer_norm must be"), ("goals", "future", "goals must be")])
def test_config_errors(field, value, match):
    with pytest.raises(ConfigError, match=match):
        crl.CRLConfig(**{field: value})


@pytest.mark.parametrize("goal", ["angle", None, 3])
def test_goals_must_be_states(goal):
    data = reference.line_task(0, 16, 2, goal if goal != 3 else "vector")
    if goal == 3:
        data = data.replace(g=jnp.zeros((16, 3)))
    agent = crl.make(crl.CRLConfig(**TINY), Problem(action_length=0.1, action_set="box"))
    with pytest.raises(ValueError, match="goals must be states"):
        agent.init(jax.random.PRNGKey(0), data)
