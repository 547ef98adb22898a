"""Hierarchical implicit Q-learning (:mod:`lazyq_jax.agents.hiql`), OGBench's ``hiql`` agent.

* the three losses against an independent NumPy (float64) re-computation with tiny networks
  (the length-normalised goal representation, the twin value on it, both AWR actors);
* which parameters each loss differentiates (OGBench's stored parameters in the actors'
  weights and targets, the target value sharing the online representation) and the Polyak
  target of the value heads;
* the minibatches as OGBench's ``HGCDataset``: subgoals ``subgoal_steps`` ahead (clipped to the
  trajectory's end, and to the high-level goal for the high-level targets); with
  ``actor_p_randomgoal`` (OGBench's stitch setting) the high-level goals and targets against a
  NumPy copy of ``HGCDataset.sample`` on three hand-made trajectories;
* learning on random walks along a line: the two levels together move towards the goal;
* config and data validation.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_crl import walks
from test_gc_agents import REACH, C, f64, member, np_expectile, np_log_prob, np_mlp, reach_probes
from test_goals import ogbench_draws

from lazyq_jax import agents
from lazyq_jax.agents import hiql, reference
from lazyq_jax.agents.base import Problem, Spec
from lazyq_jax.config import ConfigError
from lazyq_jax.types import Transitions

TINY = {"steps": 7, "batch_size": 16, "width": 8, "depth": 2, "blocks": 3, "rep_dim": 3,
        "subgoal_steps": 4}


def np_rep(p, s, g, scale):
    u = np_mlp(p["rep"], np.concatenate([s / scale, g], 1), True)
    return u / np.linalg.norm(u, axis=1, keepdims=True) * np.sqrt(u.shape[1])


def np_values(p, value, s, g, scale):
    """``[2, B]``: both heads on ``(s, z(s, g))``."""
    x = np.concatenate([s / scale, np_rep(p, s, g, scale)], 1)
    return np.stack([np_mlp(member(value, e), x, True)[:, 0] for e in range(2)])


def tiny(problem, seed=0, n=6, **extra):
    """``(agent, params, target, (value, low, high) batches)``: tiny networks, a target
    value from another key, hand-made batches whose goals are states."""
    agent = hiql.make(hiql.HIQLConfig(**{**TINY, **extra}), problem)
    rng = np.random.default_rng(seed)
    c = problem.action_length
    f = lambda x: jnp.asarray(x, jnp.float32)
    s = rng.uniform(-2, 2, (n, 2))
    a = rng.uniform(-c, c, (n, 2))
    done = np.array([False, True, False, False, True, False])[:n]
    b = Transitions(s=f(s), a=f(a), s_next=f(s + a), r=f(done - 1.0),
                    g=f(rng.uniform(-2, 2, (n, 2))), done=jnp.asarray(done))
    low = b.replace(g=f(s + rng.uniform(-0.5, 0.5, (n, 2))))
    high = b.replace(g=f(rng.uniform(-2, 2, (n, 2))), s_next=f(s + rng.uniform(-0.5, 0.5, (n, 2))))
    init = jax.jit(agent.init_model, static_argnums=1)
    model, other = init(jax.random.PRNGKey(1), Spec.of(b)), init(jax.random.PRNGKey(2), Spec.of(b))
    params = model["params"]
    for name in ("low", "high"):  # actor heads scaled up (the clip and the log-densities exercised)
        last = f"Dense_{TINY['depth'] - 1}"
        head = params[name]["params"][last]
        params = {**params, name: {"params": {**params[name]["params"],
                                              last: {**head, "kernel": head["kernel"] * 300.0}}}}
    return agent, params, other["target_value"], (b, low, high)


def test_losses_match_numpy():
    problem = Problem(action_length=0.5, action_set="box", state_scale=2.0)
    agent, params, target, (b, low, high) = tiny(problem, expectile=0.8, low_alpha=0.7, high_alpha=1.3)
    cfg, sc = agent.config, problem.state_scale
    _, metrics = jax.jit(agent.loss)(params, target, b, low, high)
    p, t = f64(params), f64(target)
    b, low, high = f64(b), f64(low), f64(high)

    next_t = np_values(p, t, b.s_next, b.g, sc)
    m = 1.0 - b.done
    q = b.r + cfg.gamma * m * next_t.min(0)
    adv = q - np_values(p, t, b.s, b.g, sc).mean(0)
    q_i = b.r + cfg.gamma * m * next_t
    v_i = np_values(p, p["value"], b.s, b.g, sc)
    value_loss = sum(np_expectile(adv, q_i[e] - v_i[e], 0.8).mean() for e in range(2))
    np.testing.assert_allclose(metrics["value_loss"], value_loss, rtol=1e-5)

    def weight(bb, alpha):
        a = np_values(p, p["value"], bb.s_next, bb.g, sc).mean(0) - np_values(p, p["value"], bb.s, bb.g, sc).mean(0)
        return np.minimum(np.exp(alpha * a), 100.0)

    c = problem.action_length
    z = np_rep(p, low.s, low.g, sc)
    mean = c * np_mlp(p["low"], np.concatenate([low.s / sc, z], 1), False)
    assert (np.abs(mean) > c).any()  # the action box is exercised through the log-density
    low_loss = -np.mean(weight(low, 0.7) * np_log_prob(problem, mean, low.a))
    np.testing.assert_allclose(metrics["low_actor_loss"], low_loss, rtol=1e-5)

    target_rep = np_rep(p, high.s, high.s_next, sc)
    mean_h = np_mlp(p["high"], np.concatenate([high.s / sc, high.g], 1), False)
    high_loss = -np.mean(weight(high, 1.3) * -0.5 * np.sum((mean_h - target_rep) ** 2, 1))
    np.testing.assert_allclose(metrics["high_actor_loss"], high_loss, rtol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(target_rep, axis=1), np.sqrt(cfg.rep_dim), rtol=1e-12)

    # acting: the high level's mean length-normalised, the low level's mean at it, clipped
    state = agent.init(jax.random.PRNGKey(0), b)
    state = state.replace(model={**state.model, "params": params})
    mh = np_mlp(p["high"], np.concatenate([b.s / sc, b.g], 1), False)
    zh = mh / np.linalg.norm(mh, axis=1, keepdims=True) * np.sqrt(cfg.rep_dim)
    want = np.clip(c * np_mlp(p["low"], np.concatenate([b.s / sc, zh], 1), False), -c, c)
    got = agent.policy(state)(None, jnp.asarray(b.s, jnp.float32), jnp.asarray(b.g, jnp.float32))
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-6)


def test_each_loss_differentiates_what_ogbench_does():
    """The value loss moves the representation and the heads (not through the target's
    terms); each actor moves itself only; the target follows the heads by Polyak averaging
    and holds no representation of its own."""
    agent, params, target, (b, low, high) = tiny(Problem(action_length=0.5, action_set="box"))
    nonzero = lambda tree: any(bool(jnp.any(x != 0)) for x in jax.tree.leaves(tree))
    grads = {"value": jax.grad(lambda p: agent.value_loss(p, target, b)[0])(params),
             "low": jax.grad(lambda p: agent.low_actor_loss(p, low)[0])(params),
             "high": jax.grad(lambda p: agent.high_actor_loss(p, high)[0])(params)}
    assert {k for k in params if nonzero(grads["value"][k])} == {"rep", "value"}
    assert {k for k in params if nonzero(grads["low"][k])} == {"low"}
    assert {k for k in params if nonzero(grads["high"][k])} == {"high"}
    # the target's terms do not reach the representation (OGBench's target value shares the
    # stored goal_rep): the gradient in "rep" is that of the online term alone
    m, cfg = 1.0 - b.done.astype(jnp.float32), agent.config
    next_t = agent.values(params["rep"], target, b.s_next, b.g)
    adv = b.r + cfg.gamma * m * next_t.min(0) - agent.values(params["rep"], target, b.s, b.g).mean(0)
    q_i = b.r + cfg.gamma * m * next_t
    online = lambda rep: jnp.sum(jnp.mean(jnp.where(adv >= 0, cfg.expectile, 1 - cfg.expectile) * (
        q_i - agent.values(rep, params["value"], b.s, b.g)) ** 2, axis=1))
    for got, want in zip(jax.tree.leaves(grads["value"]["rep"]), jax.tree.leaves(jax.grad(online)(params["rep"])),
                         strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-7)

    model = {"params": params, "target_value": target, "opt": agent.optimizer.init(params)}
    new, _ = jax.jit(agent.update)(model, (b, low, high), jax.random.PRNGKey(0), jnp.int32(0))
    tau = agent.config.tau
    want = jax.tree.map(lambda tp, p: (1 - tau) * tp + tau * p, target, params["value"])
    for got, w in zip(jax.tree.leaves(new["target_value"]), jax.tree.leaves(want), strict=True):
        np.testing.assert_allclose(got, w, rtol=1e-6, atol=1e-7)
    assert set(new) == {"params", "target_value", "opt"}


def test_minibatches_are_hgcdatasets():
    """Value goals as GCIVL's; the low level's subgoal ``subgoal_steps`` later (or the
    trajectory's last state); the high level's goal a later state of the same trajectory and
    its target ``subgoal_steps`` later but not past that goal."""
    n_traj, length, k = 40, 60, 7
    n = n_traj * length
    idx = np.arange(n)
    s = np.stack([idx, idx // length], -1).astype(np.float32)
    data = Transitions(s=jnp.asarray(s), a=jnp.zeros((n, 2)), s_next=jnp.asarray(s + 1),
                       r=-jnp.ones(n), g=jnp.asarray(s), done=jnp.zeros(n, bool),
                       traj_last=jnp.asarray((idx // length + 1) * length - 1, jnp.int32))
    agent = hiql.make(hiql.HIQLConfig(**{**TINY, "subgoal_steps": k}), Problem(action_length=1.0, action_set="box"))
    rows = jax.random.randint(jax.random.PRNGKey(0), (50_000,), 0, n)
    value, low, high = agent.batch(data, rows, jax.random.PRNGKey(1), jnp.int32(n))
    r = np.asarray(rows)
    last = (r // length + 1) * length - 1
    g_v, g_l, g_h, t_h = (np.asarray(x[:, 0]).astype(int) for x in (value.g, low.g, high.g, high.s_next))
    np.testing.assert_array_equal(g_l, np.minimum(r + k, last))
    assert ((g_h // length) == (r // length)).all() and (g_h >= r).all()
    np.testing.assert_array_equal(t_h, np.minimum(r + k, g_h))
    np.testing.assert_array_equal(np.asarray(value.r), (g_v == r) - 1.0)
    cur = (g_v == r).mean()  # p_cur 0.2, plus the geometric draws on a trajectory's last row
    tol = 5 * np.sqrt(0.16 / len(r))
    assert 0.2 - tol <= cur <= 0.2 + 0.5 / length + 0.3 / n + tol
    np.testing.assert_array_equal(np.asarray(low.a), np.asarray(data.a)[r])


def ogbench_high_goals(idxs, terminal_locs, subgoal_steps, actor_p_randomgoal, distances,
                       high_random_goal_idxs, rand):
    """OGBench's ``HGCDataset.sample`` (``impls/utils/datasets.py``), the high-level actor goals
    and targets, line for line (``actor_geom_sample`` False), its ``np.random`` draws given
    (``distances``, ``high_random_goal_idxs``: ``get_random_idxs``, ``rand``: the
    ``pick_random`` uniform) and the uniform offsets in float32 (our draws' precision)."""
    final_state_idxs = terminal_locs[np.searchsorted(terminal_locs, idxs)]
    f32 = np.float32
    high_traj_goal_idxs = np.round(
        np.minimum(idxs + 1, final_state_idxs).astype(f32) * distances
        + final_state_idxs.astype(f32) * (f32(1) - distances)
    ).astype(int)
    high_traj_target_idxs = np.minimum(idxs + subgoal_steps, high_traj_goal_idxs)
    high_random_target_idxs = np.minimum(idxs + subgoal_steps, final_state_idxs)
    pick_random = rand < actor_p_randomgoal
    high_goal_idxs = np.where(pick_random, high_random_goal_idxs, high_traj_goal_idxs)
    high_target_idxs = np.where(pick_random, high_random_target_idxs, high_traj_target_idxs)
    return high_goal_idxs, high_target_idxs


@pytest.mark.parametrize("p", [0.5, 0.0, 1.0])
def test_random_high_goals_are_hgcdatasets(p):
    """``actor_p_randomgoal = p``: the high-level goals and targets of :meth:`HIQL.batch` on
    three hand-made trajectories equal OGBench's ``HGCDataset.sample``
    (:func:`ogbench_high_goals`) fed our draws (its ``pick_random = rand < p`` with ``rand``
    our ``1 - u``, ``u`` the trajectory-or-random uniform of
    :func:`~lazyq_jax.agents.goals.sample_goal_rows`); a random goal's target is
    ``subgoal_steps`` ahead on the row's own trajectory (clipped to its end), a trajectory
    goal's no later than the goal; about ``p`` of the goals random (5 binomial sigmas)."""
    lengths, k = [9, 14, 6], 4
    terminal_locs = np.cumsum(lengths) - 1
    last = np.repeat(terminal_locs, lengths)
    n = len(last)
    idx = np.arange(n)
    s = np.stack([idx, np.repeat(np.arange(len(lengths)), lengths)], -1).astype(np.float32)
    data = Transitions(s=jnp.asarray(s), a=jnp.zeros((n, 2)), s_next=jnp.asarray(s + 1),
                       r=-jnp.ones(n), g=jnp.asarray(s), done=jnp.zeros(n, bool),
                       traj_last=jnp.asarray(last, jnp.int32))
    agent = hiql.make(hiql.HIQLConfig(**{**TINY, "subgoal_steps": k, "actor_p_randomgoal": p}),
                      Problem(action_length=1.0, action_set="box"))
    b = 20_000
    rows = jax.random.randint(jax.random.PRNGKey(0), (b,), 0, n)
    key = jax.random.PRNGKey(1)
    _, low, high = jax.jit(agent.batch)(data, rows, key, jnp.int32(n))
    goal, target = (np.asarray(x[:, 0]).astype(int) for x in (high.g, high.s_next))
    r = np.asarray(rows)
    draws = ogbench_draws(jax.random.split(key)[1], rows.shape, n, agent.config.gamma)
    want_goal, want_target = ogbench_high_goals(r, terminal_locs, k, p, draws["distances"],
                                                draws["random_goal_idxs"], 1.0 - draws["u_traj"])
    np.testing.assert_array_equal(goal, want_goal)
    np.testing.assert_array_equal(target, want_target)
    np.testing.assert_array_equal(np.asarray(high.s), s[r])
    np.testing.assert_array_equal(np.asarray(low.g[:, 0]).astype(int), np.minimum(r + k, last[r]))
    # without the draws: a goal outside the row's future [r, last] is a random one
    outside = (goal < r) | (goal > last[r])
    np.testing.assert_array_equal(target[outside], np.minimum(r + k, last[r])[outside])
    inside = ~outside & (target != np.minimum(r + k, last[r]))  # only trajectory goals
    np.testing.assert_array_equal(target[inside], np.minimum(r + k, goal)[inside])
    expect_outside = p * (1 - np.mean(last[r] - r + 1) / n)
    assert abs(outside.mean() - expect_outside) <= 5 * np.sqrt(expect_outside * (1 - expect_outside) / b)
    if p == 0.0:  # OGBench's default: every goal in the row's future, the target before it
        assert not outside.any()
        np.testing.assert_array_equal(target, np.minimum(r + k, goal))


# Measured over 4 seeds (key and data), 3,000 steps: sign agreement with the optimal move
# 1.00, mean a . sign(g - s) / c 0.77-0.85.
LEARN = {"batch_size": 256, "width": 32, "depth": 3, "blocks": 1, "learning_rate": 1e-3,
         "steps": 3000, "gamma": 0.9, "subgoal_steps": 5, "rep_dim": 4}


def test_hiql_moves_towards_the_goal():
    """Trained on uniformly random walks: the high level's subgoal and the low level's action
    together move towards the goal, and V ranks goals by the moves they need."""
    agent = hiql.make(hiql.HIQLConfig(**LEARN), REACH)
    state, metrics = jax.jit(agent.train)(jax.random.PRNGKey(0), walks(0))
    assert all(np.all(np.isfinite(np.asarray(v))) for v in jax.tree.leaves(metrics))
    s, g, sign = reach_probes()
    actions = np.asarray(agent.policy(state)(None, s, g))[:, 0]
    assert np.all(np.abs(actions) <= C)
    assert np.mean(np.sign(actions) == sign) >= 0.9
    assert np.mean(actions * sign) > 0.5 * C


def test_defaults_are_ogbenchs():
    cfg = hiql.HIQLConfig()
    assert (cfg.learning_rate, cfg.batch_size, cfg.width, cfg.depth, cfg.gamma, cfg.tau,
            cfg.expectile, cfg.low_alpha, cfg.high_alpha, cfg.subgoal_steps, cfg.rep_dim,
            cfg.layer_norm, cfg.actor_p_randomgoal) == (3e-4, 1024, 512, 4, 0.99, 0.005, 0.7, 3.0,
                                                        3.0, 25, 10, True, 0.0)
    assert agents.config_class("hiql") is hiql.HIQLConfig and "hiql" in agents.BASELINES


@pytest.mark.parametrize("field, value, match", [
    ("subgoal_steps", 0, "subgoal_steps must be"), ("rep_dim", 0, "rep_dim must be"),
    ("expectile", 1.0, "expectile must be"), ("low_alpha", -1.0, "low_alpha must be"),
    ("tau", 0.0, "tau must be"), ("layer_norm", "yes", "layer_norm must be"),
    ("actor_p_randomgoal", -0.1, r"HIQLConfig\.actor_p_randomgoal must be a finite number in \[0, 1\]"),
    ("actor_p_randomgoal", 1.5, r"actor_p_randomgoal must be .* got 1\.5"),
    ("actor_p_randomgoal", float("nan"), "actor_p_randomgoal must be")])
def test_config_errors(field, value, match):
    with pytest.raises(ConfigError, match=match):
        hiql.HIQLConfig(**{field: value})


def test_goals_must_be_states_and_the_data_trajectories():
    agent = hiql.make(hiql.HIQLConfig(**TINY), Problem(action_length=0.1, action_set="box"))
    with pytest.raises(ValueError, match="goals must be states"):
        agent.init(jax.random.PRNGKey(0), reference.line_task(0, 16, 2, "angle"))
    rows = walks(0, 4, 10)
    plain = dataclasses.replace(rows, traj_last=None)
    state = agent.init(jax.random.PRNGKey(0), plain)
    with pytest.raises(ValueError, match="needs trajectory data"):
        agent.run_block(state, plain)
