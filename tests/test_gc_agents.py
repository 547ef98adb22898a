"""OGBench's goal-conditioned baselines (:mod:`lazyq_jax.agents.gcivl`, ``gciql``, ``gcbc``).

* every loss against an independent NumPy (float64) re-computation with the same tiny
  networks' parameters, in the box and on the sphere;
* which parameters each loss differentiates (OGBench's stored vs gradient parameters)
  and the target update (from the online parameters before the step, as OGBench);
* the expectile loss's minimiser against the expectile of a sample (bisection);
* learning on a 1-D reaching task with a known optimum (move towards the goal), with
  OGBench's reward convention (``r = success - 1``, ``done = success``, success when the
  current state is within ``TOL`` of the goal) and goals drawn as OGBench's value goals
  (current state 0.2, nearby 0.5, random 0.3): GCIVL and GCIQL learn to move towards the
  goal from uniformly random behaviour, GCBC imitates a noisy expert;
* ``actor_p_randomgoal`` (OGBench's stitch datasets' actor goals) in GCIVL's, GCIQL's, QRL's
  and CRL's actor minibatches, and its validation;
* config validation, the registry, and ``jax.jit(agent.train)`` of the defaults.
"""

import dataclasses
import math
import os
import re
from concurrent.futures import ThreadPoolExecutor

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lazyq_jax import agents
from lazyq_jax.agents import crl, gcbc, gciql, gcivl, qrl, reference
from lazyq_jax.agents.base import Problem, Spec
from lazyq_jax.config import ConfigError
from lazyq_jax.types import Transitions

CONFIGS = {"gcivl": gcivl.GCIVLConfig, "gciql": gciql.GCIQLConfig, "gcbc": gcbc.GCBCConfig}
MODULES = {"gcivl": gcivl, "gciql": gciql, "gcbc": gcbc}
TINY = {"steps": 7, "batch_size": 16, "width": 8, "depth": 2, "blocks": 3}

# ----------------------------------------------------------------------------- NumPy reference


def f64(tree):
    return jax.tree.map(lambda x: np.asarray(x, np.float64), tree)


def np_gelu(x):
    """flax's ``nn.gelu`` (the tanh approximation, OGBench's activation)."""
    return 0.5 * x * (1.0 + np.tanh(np.sqrt(2.0 / np.pi) * (x + 0.044715 * x ** 3)))


def np_layer_norm(x, p):
    mean = x.mean(-1, keepdims=True)
    var = ((x - mean) ** 2).mean(-1, keepdims=True)
    return (x - mean) / np.sqrt(var + 1e-6) * p["scale"] + p["bias"]


def np_mlp(params, x, layer_norm):
    """OGBench's MLP: (Dense, GELU[, LayerNorm]) x (depth - 1), Dense."""
    p = params["params"]
    depth = sum(k.startswith("Dense_") for k in p)
    for i in range(depth - 1):
        x = np_gelu(x @ p[f"Dense_{i}"]["kernel"] + p[f"Dense_{i}"]["bias"])
        if layer_norm:
            x = np_layer_norm(x, p[f"LayerNorm_{i}"])
    last = p[f"Dense_{depth - 1}"]
    return x @ last["kernel"] + last["bias"]


def member(params, i):
    return jax.tree.map(lambda x: x[i], params)


def np_twin(params, x):
    """``[2, B]``: both members of a stacked twin (value or critic) network."""
    return np.stack([np_mlp(member(params, i), x, True)[:, 0] for i in range(2)])


def np_log_prob(problem, mean, a):
    c = problem.action_length
    if problem.action_set == "box":  # N(mean, c) per component, without -n/2 log(2 pi)
        return -0.5 * np.sum(((mean - a) / c) ** 2, -1)
    unit = lambda v: v / np.linalg.norm(v, axis=-1, keepdims=True)
    return np.sum(unit(mean) * unit(a), -1)  # von Mises-Fisher, kappa = 1


def np_project(problem, a):
    c = problem.action_length
    if problem.action_set == "box":
        return np.clip(a, -c, c)
    return c * a / np.linalg.norm(a, axis=-1, keepdims=True)


def np_expectile(adv, diff, tau):
    return np.where(adv >= 0, tau, 1 - tau) * diff ** 2


def tiny_batch(problem, seed=0, n=6):
    """A hand-made batch: 2-D states and goals, 2-D actions of the set, two terminal rows."""
    rng = np.random.default_rng(seed)
    c = problem.action_length
    s = rng.uniform(-2, 2, (n, 2))
    g = rng.uniform(-2, 2, (n, 2))
    if problem.action_set == "box":
        a = rng.uniform(-c, c, (n, 2))
    else:
        a = rng.normal(size=(n, 2))
        a = c * a / np.linalg.norm(a, axis=1, keepdims=True)
    done = np.array([False, True, False, False, True, False])[:n]
    f = lambda x: jnp.asarray(x, jnp.float32)
    return Transitions(s=f(s), a=f(a), s_next=f(s + a), r=f(done - 1.0), g=f(g),
                       done=jnp.asarray(done))


def np_inputs(problem, b):
    b = f64(b)
    x = np.concatenate([b.s / problem.state_scale, b.g], 1)
    xn = np.concatenate([b.s_next / problem.state_scale, b.g], 1)
    return b, x, xn


def scaled_actor(params, factor):
    """The actor's mean head scaled by ``factor`` (OGBench's init scale 1e-2 keeps every
    mean far inside the box; larger means exercise the clip)."""
    last = f"Dense_{TINY['depth'] - 1}"
    actor = jax.tree.map(lambda x: x, params["actor"])
    actor["params"][last] = {"kernel": actor["params"][last]["kernel"] * factor,
                             "bias": actor["params"][last]["bias"]}
    return {**params, "actor": actor}


SETS = [Problem(action_length=0.5, action_set="box", state_scale=2.0),
        Problem(action_length=0.5, action_set="ball", state_scale=2.0)]


def models(name, problem, **extra):
    """``(agent, params, target, batch)``: tiny networks, the target network initialised
    from another key (so that online and target differ)."""
    agent = MODULES[name].make(CONFIGS[name](**TINY, **extra), problem)
    b = tiny_batch(problem)
    spec = Spec.of(b)
    init = jax.jit(agent.init_model, static_argnums=1)
    model, other = init(jax.random.PRNGKey(1), spec), init(jax.random.PRNGKey(2), spec)
    params = scaled_actor(model["params"], 300.0)
    target = {"gcivl": lambda: other["params"]["value"],
              "gciql": lambda: other["params"]["critic"], "gcbc": lambda: None}[name]()
    return agent, params, target, b


# ----------------------------------------------------------------------------- losses


@pytest.mark.parametrize("problem", SETS, ids=lambda p: p.action_set)
def test_gcivl_losses_match_numpy(problem):
    agent, params, target, batch = models("gcivl", problem, expectile=0.8)
    p, t = f64(params), f64(target)
    b, x, xn = np_inputs(problem, batch)
    # alpha such that exactly the largest advantage's exp(alpha A) exceeds the clip 100
    top = np.sort(np_twin(p["value"], xn).mean(0) - np_twin(p["value"], x).mean(0))[-2:]
    assert top[1] > 0
    alpha = math.log(100.0) / (top[1] - 0.5 * (top[1] - max(top[0], 0.0)))
    agent = gcivl.make(dataclasses.replace(agent.config, alpha=alpha), problem)
    cfg, c = agent.config, problem.action_length
    _, metrics = jax.jit(agent.loss)(params, target, batch)
    m = 1.0 - b.done
    next_v_t = np_twin(t, xn)
    q = b.r + cfg.gamma * m * next_v_t.min(0)
    adv = q - np_twin(t, x).mean(0)
    q_i = b.r + cfg.gamma * m * next_v_t
    v_i = np_twin(p["value"], x)
    value_loss = sum(np_expectile(adv, q_i[i] - v_i[i], 0.8).mean() for i in range(2))
    assert (adv >= 0).any() and (adv < 0).any()  # both expectile weights are exercised

    adv_pi = np_twin(p["value"], xn).mean(0) - v_i.mean(0)
    weight = np.minimum(np.exp(alpha * adv_pi), 100.0)
    assert np.sum(weight == 100.0) == 1  # the clip is exercised
    mean = c * np_mlp(p["actor"], x, False)
    actor_loss = -np.mean(weight * np_log_prob(problem, mean, b.a))
    np.testing.assert_allclose(metrics["value_loss"], value_loss, rtol=1e-5)
    np.testing.assert_allclose(metrics["actor_loss"], actor_loss, rtol=1e-5)
    np.testing.assert_allclose(metrics["adv"], adv_pi.mean(), rtol=1e-5, atol=1e-6)


def test_gcivl_value_fn_is_the_twin_mean():
    problem = SETS[0]
    agent = gcivl.make(gcivl.GCIVLConfig(**TINY), problem)
    b = tiny_batch(problem)
    state = agent.init(jax.random.PRNGKey(3), b)
    _, x, _ = np_inputs(problem, b)
    expected = np_twin(f64(state.model["params"]["value"]), x).mean(0)
    np.testing.assert_allclose(agent.value_fn(state)(b.s, b.g), expected, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("problem", SETS, ids=lambda p: p.action_set)
def test_gciql_losses_match_numpy(problem):
    agent, params, target, batch = models("gciql", problem, alpha=0.7, expectile=0.8)
    cfg, c = agent.config, problem.action_length
    b, x, xn = np_inputs(problem, batch)
    xa = np.concatenate([x, b.a / c], 1)
    q_t = np_twin(f64(target), xa).min(0)
    # V's output bias shifted to the median of Q^t - V: rows on both sides of the expectile
    last = f"Dense_{TINY['depth'] - 1}"
    shift = np.median(q_t - np_mlp(f64(params)["value"], x, True)[:, 0])
    head = params["value"]["params"][last]
    params = {**params, "value": {"params": {**params["value"]["params"],
                                             last: {**head, "bias": head["bias"] + shift}}}}
    _, metrics = jax.jit(agent.loss)(params, target, batch)
    p = f64(params)
    v = np_mlp(p["value"], x, True)[:, 0]
    value_loss = np_expectile(q_t - v, q_t - v, 0.8).mean()
    assert (q_t >= v).any() and (q_t < v).any()

    y = b.r + cfg.gamma * (1.0 - b.done) * np_mlp(p["value"], xn, True)[:, 0]
    critic_loss = np.mean(np.sum((np_twin(p["critic"], xa) - y) ** 2, 0))

    mean = c * np_mlp(p["actor"], x, False)
    q_actions = np_project(problem, mean)
    if problem.action_set == "box":
        assert (np.abs(mean) > c).any() and (np.abs(mean) < c).any()  # the clip is exercised
    q_pi = np_twin(p["critic"], np.concatenate([x, q_actions / c], 1)).min(0)
    q_loss = -q_pi.mean() / (np.abs(q_pi).mean() + 1e-6)
    bc_loss = -np.mean(0.7 * np_log_prob(problem, mean, b.a))
    np.testing.assert_allclose(metrics["value_loss"], value_loss, rtol=1e-5)
    np.testing.assert_allclose(metrics["critic_loss"], critic_loss, rtol=1e-5)
    np.testing.assert_allclose(metrics["q_loss"], q_loss, rtol=1e-5)
    np.testing.assert_allclose(metrics["bc_loss"], bc_loss, rtol=1e-5)
    np.testing.assert_allclose(metrics["actor_loss"], q_loss + bc_loss, rtol=1e-5)


@pytest.mark.parametrize("problem", SETS, ids=lambda p: p.action_set)
def test_gcbc_loss_and_actions_match_numpy(problem):
    agent, params, _, batch = models("gcbc", problem)
    loss, _ = jax.jit(agent.loss)(params, batch)
    p = f64(params)
    b, x, _ = np_inputs(problem, batch)
    mean = problem.action_length * np_mlp(p["actor"], x, False)
    np.testing.assert_allclose(loss, -np.mean(np_log_prob(problem, mean, b.a)), rtol=1e-5)
    # acting: the mode projected onto the action set (OGBench: clip(mode, -1, 1))
    acts = agent.actions({"params": params}, batch.s, batch.g)
    np.testing.assert_allclose(acts, np_project(problem, mean), rtol=1e-5, atol=1e-7)


def test_box_log_prob_is_ogbench_gaussian_up_to_a_constant():
    """In the box our log-likelihood is OGBench's ``N(u, 1).log_prob(a / c)`` plus
    ``n_a / 2 log(2 pi)`` (for actions in units of ``c``)."""
    problem = SETS[0]
    agent, params, _, batch = models("gcbc", problem)
    _, metrics = jax.jit(agent.loss)(params, batch)
    b, x, _ = np_inputs(problem, batch)
    u = np_mlp(f64(params)["actor"], x, False)
    z = b.a / problem.action_length - u
    ogbench = np.mean(-0.5 * np.sum(z ** 2, -1) - 0.5 * z.shape[1] * np.log(2 * np.pi))
    np.testing.assert_allclose(metrics["bc_log_prob"] - np.log(2 * np.pi), ogbench, rtol=1e-5)


def zero_tree(tree):
    return all(not np.any(np.asarray(x)) for x in jax.tree.leaves(tree))


def loss_grads(agent, params, target, b, losses):
    """``{loss: its gradient}`` over all of ``params`` (one compiled program)."""
    fns = {"value": lambda p: agent.value_loss(p, target, b)[0],
           "critic": lambda p: agent.critic_loss(p, b)[0],
           "actor": lambda p: agent.actor_loss(p, b)[0]}
    return jax.jit(lambda p: {k: jax.grad(fns[k])(p) for k in losses})(params)


@pytest.mark.parametrize("name, losses", [("gcivl", ("value", "actor")),
                                          ("gciql", ("value", "critic", "actor"))])
def test_each_loss_differentiates_only_its_network(name, losses):
    """OGBench evaluates the other networks with their stored parameters (no gradient):
    the actor losses move the actor only, GCIQL's critic loss the critics only."""
    grads = loss_grads(*models(name, SETS[0]), losses)
    for loss in losses:
        for net in losses:
            assert zero_tree(grads[loss][net]) == (net != loss), (loss, net)


@pytest.mark.parametrize("name, target", [("gcivl", "value"), ("gciql", "critic")])
def test_target_follows_the_online_network_before_the_step(name, target):
    agent, params, tgt, b = models(name, SETS[0], tau=0.25)
    model = {"params": params, f"target_{target}": tgt, "opt": agent.optimizer.init(params)}
    new, _ = jax.jit(agent.update)(model, b, jax.random.PRNGKey(0), jnp.int32(0))
    want = jax.tree.map(lambda t, o: 0.75 * t + 0.25 * o, tgt, params[target])
    for got, expected in zip(jax.tree.leaves(new[f"target_{target}"]), jax.tree.leaves(want),
                             strict=True):
        np.testing.assert_allclose(got, expected, rtol=1e-6, atol=1e-7)
    assert not zero_tree(jax.tree.map(lambda a, b: a - b, new["params"], params))


def test_gcivl_hard_target_copies_the_online_network_before_the_loss():
    """``target_period = 3``: steps 0 and 3 copy the online value network into the target
    before their loss (lazy Q's cycles), steps 1 and 4 keep the target as it is."""
    agent, params, tgt, b = models("gcivl", SETS[0], target_period=3)
    model = {"params": params, "target_value": tgt, "opt": agent.optimizer.init(params)}
    update = jax.jit(agent.update)
    for step, copied in ((0, True), (1, False), (3, True), (4, False)):
        new, metrics = update(model, b, jax.random.PRNGKey(0), jnp.int32(step))
        want = params["value"] if copied else tgt
        for got, expected in zip(jax.tree.leaves(new["target_value"]), jax.tree.leaves(want),
                                 strict=True):
            np.testing.assert_array_equal(got, expected)
        # the step's value loss is the one with that target (the copy came first)
        _, info = agent.loss(params, want, b)
        np.testing.assert_allclose(metrics["value_loss"], info["value_loss"], rtol=1e-5)
        _, other = agent.loss(params, tgt if copied else params["value"], b)
        assert not np.isclose(metrics["value_loss"], other["value_loss"], rtol=1e-3)


# ----------------------------------------------------------------------------- expectile


def closed_form_expectile(x, tau):
    """The ``tau``-expectile ``e`` of a sample: ``tau E(x - e)_+ = (1 - tau) E(e - x)_+``
    (the root of a decreasing function of ``e``), by bisection in float64."""
    lo, hi = x.min(), x.max()
    for _ in range(200):
        e = 0.5 * (lo + hi)
        if tau * np.maximum(x - e, 0).sum() > (1 - tau) * np.maximum(e - x, 0).sum():
            lo = e
        else:
            hi = e
    return 0.5 * (lo + hi)


def test_expectile_loss_minimiser_is_the_expectile():
    x = np.random.default_rng(3).gamma(2.0, 1.5, 64) - 2.0
    taus = np.array([0.1, 0.5, 0.7, 0.9])

    @jax.jit
    def minimise(x, taus):
        def one(tau):
            loss = lambda v: jnp.mean(gcivl.expectile_loss(x - v, x - v, tau))
            lr = 0.5 / jnp.maximum(tau, 1 - tau)  # <= 1 / the curvature 2 max(tau, 1 - tau)
            return jax.lax.fori_loop(0, 500, lambda _, v: v - lr * jax.grad(loss)(v),
                                     jnp.float32(0.0))
        return jax.vmap(one)(taus)

    got = np.asarray(minimise(jnp.asarray(x, jnp.float32), jnp.asarray(taus, jnp.float32)))
    want = np.array([closed_form_expectile(x, t) for t in taus])
    np.testing.assert_allclose(want[1], x.mean(), rtol=1e-9)  # the 0.5-expectile: the mean
    assert np.all(np.diff(want) > 0)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5)


# ----------------------------------------------------------------------------- learning

C, TOL = 0.1, 0.05
REACH = Problem(action_length=C, action_set="box")
# Measured over 4 seeds (key, data) (sign agreement with the optimal move on 500 probes,
# mean a . sign(g - s) / c): gcivl 1.00, 0.29-0.31; gciql 1.00, 0.72-0.91; gcbc 1.00,
# 0.56-0.65 (the expert's mean: 0.7).  Compiles dominate (~3-9 s each on 2 cores).
LEARN = {"batch_size": 256, "width": 64, "depth": 2, "blocks": 1, "learning_rate": 1e-3}
LEARN_OVERRIDES = {
    # tau 0.05: 1,000 steps span ~50 target time constants (the data are <= 20 moves long)
    "gcivl": {"steps": 1000, "tau": 0.05},
    "gciql": {"steps": 1000, "tau": 0.05},
    # depth 3: one hidden layer fits the expert's step at g = s too slowly (0.3 c at 1,000)
    "gcbc": {"steps": 1000, "depth": 3},
}
EXPERT = 0.7  # the noisy expert moves towards the goal with probability 0.7, else at random


def reach_task(seed, n, expert=False):
    """1-D reaching: ``s`` in [-1, 1], a move ``a`` in [-c, c] gives ``s' = s + a``; goals
    (vectors ``[n, 1]``) as OGBench's value goals: the current state (p 0.2), a state
    within 0.5 (p 0.5) or a random one (p 0.3); ``r = success - 1``, ``done = success``
    with success ``|s - g| <= TOL`` (the current state, as OGBench).  Actions uniform, or
    (``expert``) ``c sign(g - s)`` with probability 0.7, else uniform."""
    rng = np.random.default_rng(seed)
    s = rng.uniform(-1, 1, (n, 1))
    kind = rng.choice(3, (n, 1), p=[0.2, 0.5, 0.3])
    g = np.where(kind == 0, s, np.where(kind == 1, s + rng.uniform(-0.5, 0.5, (n, 1)),
                                        rng.uniform(-1, 1, (n, 1))))
    a = rng.uniform(-C, C, (n, 1))
    if expert:
        a = np.where(rng.random((n, 1)) < EXPERT, C * np.sign(g - s), a)
    success = np.abs(s - g)[:, 0] <= TOL
    f = lambda x: jnp.asarray(x, jnp.float32)
    return Transitions(s=f(s), a=f(a), s_next=f(s + a), r=f(success - 1.0), g=f(g),
                       done=jnp.asarray(success))


def reach_probes(n=500, seed=7):
    """States with the goal 0.15-0.5 away (2-5 moves): ``(s, g, sign(g - s))``."""
    rng = np.random.default_rng(seed)
    s = rng.uniform(-0.9, 0.9, (n, 1))
    g = np.clip(s + rng.uniform(0.15, 0.5, (n, 1)) * rng.choice([-1, 1], (n, 1)), -1, 1)
    return jnp.asarray(s, jnp.float32), jnp.asarray(g, jnp.float32), np.sign(g - s)[:, 0]


@pytest.fixture(scope="module")
def learned():
    """``name -> actions on the probes`` of each agent trained on the reaching task; the
    three programs compiled at once (XLA compiles release the GIL)."""
    data = {False: reach_task(1, 4000), True: reach_task(1, 4000, expert=True)}
    jobs = {}
    for name, cls in CONFIGS.items():
        agent = MODULES[name].make(cls(**{**LEARN, **LEARN_OVERRIDES[name]}), REACH)
        d = data[name == "gcbc"]
        jobs[name] = (agent, jax.jit(agent.train).lower(jax.random.PRNGKey(0), d), d)

    def run(item):
        agent, lowered, d = item
        state, metrics = lowered.compile()(jax.random.PRNGKey(0), d)
        s, g, _ = reach_probes()
        return np.asarray(agent.policy(state)(None, s, g))[:, 0], metrics

    with ThreadPoolExecutor(max_workers=min(3, os.cpu_count() or 1)) as pool:
        return dict(zip(jobs, pool.map(run, jobs.values()), strict=True))


@pytest.mark.parametrize("name", ["gcivl", "gciql"])
def test_value_methods_move_towards_the_goal(learned, name):
    actions, metrics = learned[name]
    sign = reach_probes()[2]
    assert all(np.all(np.isfinite(np.asarray(v))) for v in jax.tree.leaves(metrics))
    assert np.all(np.abs(actions) <= C)
    # the behaviour is uniform (mean 0, chance 0.5): the values must tell the direction
    assert np.mean(np.sign(actions) == sign) >= 0.9
    assert np.mean(actions * sign) > 0.15 * C


def test_gcbc_imitates_the_noisy_expert(learned):
    actions, _ = learned["gcbc"]
    sign = reach_probes()[2]
    assert np.mean(np.sign(actions) == sign) >= 0.9
    # the likelihood's maximiser is the expert's mean action 0.7 c sign(g - s)
    assert abs(np.mean(actions * sign) / C - EXPERT) < 0.25


# ----------------------------------------------------------------------------- configs


def test_defaults_are_ogbenchs():
    for name, cls in CONFIGS.items():
        cfg = cls()
        assert (cfg.learning_rate, cfg.batch_size, cfg.width, cfg.depth, cfg.gamma) == (
            3e-4, 1024, 512, 4, 0.99), name
    for cls in (gcivl.GCIVLConfig, gciql.GCIQLConfig):
        assert (cls().tau, cls().expectile, cls().layer_norm) == (0.005, 0.9, True)
    assert (gcivl.GCIVLConfig().alpha, gcivl.GCIVLConfig().max_weight) == (10.0, 100.0)
    assert gciql.GCIQLConfig().alpha == 0.003


@pytest.mark.parametrize("cls, field, value", [
    (gcivl.GCIVLConfig, "expectile", 0.0), (gcivl.GCIVLConfig, "expectile", 1.0),
    (gcivl.GCIVLConfig, "expectile", 1.5), (gcivl.GCIVLConfig, "alpha", -1.0),
    (gcivl.GCIVLConfig, "alpha", math.inf), (gcivl.GCIVLConfig, "tau", 0.0),
    (gcivl.GCIVLConfig, "tau", 1.5), (gcivl.GCIVLConfig, "max_weight", 0.0),
    (gcivl.GCIVLConfig, "layer_norm", "yes"), (gcivl.GCIVLConfig, "gamma", 1.0),
    (gcivl.GCIVLConfig, "target_period", -1), (gcivl.GCIVLConfig, "target_period", 2.5),
    (gciql.GCIQLConfig, "expectile", -0.1), (gciql.GCIQLConfig, "alpha", -0.003),
    (gciql.GCIQLConfig, "tau", -1.0), (gciql.GCIQLConfig, "layer_norm", 1),
    (gciql.GCIQLConfig, "alpha", float("nan")),
    (gcbc.GCBCConfig, "width", 0), (gcbc.GCBCConfig, "depth", 1),
    (gcbc.GCBCConfig, "learning_rate", 0.0), (gcbc.GCBCConfig, "batch_size", 2.5),
])
def test_config_errors_name_the_field(cls, field, value):
    with pytest.raises(ConfigError, match=rf"{cls.__name__}\.{field} must be"):
        cls(**{field: value})


ACTOR_GOAL_CONFIGS = [gcivl.GCIVLConfig, gciql.GCIQLConfig, qrl.QRLConfig, crl.CRLConfig]


@pytest.mark.parametrize("cls", ACTOR_GOAL_CONFIGS)
def test_actor_p_randomgoal_is_validated(cls):
    """In ``[0, 1]`` (OGBench's default 0); above 0 not with the rows' own goals."""
    assert cls().actor_p_randomgoal == 0.0
    assert cls(actor_p_randomgoal=0.5).actor_p_randomgoal == 0.5
    name = cls.__name__
    for bad in (-0.1, 1.5, float("nan"), "half"):
        with pytest.raises(ConfigError, match=rf"{name}\.actor_p_randomgoal must be a finite "
                                              rf"number in \[0, 1\], got {re.escape(repr(bad))}"):
            cls(actor_p_randomgoal=bad)
    with pytest.raises(ConfigError, match=rf"{name}\.actor_p_randomgoal=0\.5 draws random actor "
                                          r"goals .* goals='rows'"):
        cls(actor_p_randomgoal=0.5, goals="rows")
    assert cls(actor_p_randomgoal=0.0, goals="rows").goals == "rows"


@pytest.mark.parametrize("name", ["gcivl", "gciql", "qrl", "crl"])
def test_stitch_actor_goals_in_the_actor_minibatch(name):
    """``actor_p_randomgoal = 0.5`` (OGBench's stitch setting): the actor minibatch's goals are
    a random state for about half the rows (outside the row's future with probability
    ``0.5 (1 - E[last - idx + 1] / n)``, 5 binomial sigmas), the value minibatch's goals those
    of the default; with 0 every actor goal lies in the row's future."""
    n_traj, length, b = 20, 30, 20_000
    n = n_traj * length
    idx = np.arange(n)
    s = np.stack([idx, idx // length], -1).astype(np.float32)
    last = (idx // length + 1) * length - 1
    data = Transitions(s=jnp.asarray(s), a=jnp.zeros((n, 2)), s_next=jnp.asarray(s + 1),
                       r=-jnp.ones(n), g=jnp.asarray(s), done=jnp.zeros(n, bool),
                       traj_last=jnp.asarray(last, jnp.int32))
    problem = Problem(action_length=1.0, action_set="box")
    rows = jax.random.randint(jax.random.PRNGKey(0), (b,), 0, n)
    r = np.asarray(rows)

    def batch(p):
        cfg = agents.config_class(name)(**TINY, actor_p_randomgoal=p)
        agent = agents.make(name, cfg, problem=problem)
        value, actor = agent.batch(data, rows, jax.random.PRNGKey(1), jnp.int32(n))[:2]
        return np.asarray(value.g[:, 0]).astype(int), np.asarray(actor.g[:, 0]).astype(int)

    (v0, a0), (v5, a5) = batch(0.0), batch(0.5)
    np.testing.assert_array_equal(v5, v0)
    assert ((a0 >= r) & (a0 <= last[r])).all()
    outside = (a5 < r) | (a5 > last[r])
    expect = 0.5 * (1 - np.mean(last[r] - r + 1) / n)
    assert abs(outside.mean() - expect) <= 5 * np.sqrt(expect * (1 - expect) / b)


def test_registry():
    for name, cls in CONFIGS.items():
        assert name in agents.AGENTS and name in agents.BASELINES
        assert agents.config_class(name) is cls and cls.__name__ in agents.__all__
        with pytest.raises(TypeError, match=cls.__name__):
            agents.make(name, agents.IQLConfig())
    with pytest.raises(TypeError, match="GCIVLConfig"):
        agents.make("gciql", gcivl.GCIVLConfig())


@pytest.mark.parametrize("goal, action_set", [("angle", "ball"), ("vector", "box"),
                                              (None, "ball")])
def test_defaults_trace_for_every_goal_kind_and_action_set(goal, action_set):
    """``jax.eval_shape`` of ``train`` with the default (OGBench-sized) configs: every
    agent builds for angle, vector and no goals, in both action sets."""
    data = reference.line_task(0, 32, 2, goal)
    problem = Problem(action_length=0.1, action_set=action_set)
    for name in CONFIGS:
        agent = agents.make(name, None, problem=problem)
        state, metrics = jax.eval_shape(agent.train, jax.random.PRNGKey(0), data)
        kernel = state.model["params"]["actor"]["params"]["Dense_3"]["kernel"]
        assert kernel.shape == (512, 2), name
        assert all(m.shape == (agent.blocks,) for m in jax.tree.leaves(metrics)), name
        acts = jax.eval_shape(lambda st, ag=agent: ag.policy(st)(None, data.s, data.g), state)
        assert acts.shape == (32, 2), name


def test_make_gcivl_trains_under_jit():
    problem = Problem(action_length=1.0, action_set="box")
    agent = agents.make("gcivl", None, problem=problem)
    assert agent.config == gcivl.GCIVLConfig()
    data = reach_task(2, 64)
    agent = agents.make("gcivl", dataclasses.replace(agent.config, **TINY), problem=problem)
    state, metrics = jax.jit(agent.train)(jax.random.PRNGKey(0), data)
    assert int(state.step) == TINY["steps"]
    assert np.asarray(metrics["steps"]).tolist() == [3, 3, 1]
    assert all(np.all(np.isfinite(np.asarray(v))) for v in jax.tree.leaves(metrics))
    acts = np.asarray(agent.policy(state)(None, data.s, data.g))
    assert acts.shape == (64, 1) and np.all(np.abs(acts) <= 1.0)
