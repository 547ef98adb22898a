"""The offline baselines on a synthetic task with a known optimal action, and the scripted
push controller in the real env.

Synthetic task ("cross the line"): states uniform in [-1, 1]^2, goal angle g,
``u_g = (cos g, sin g)``; a move ``a`` of length c = 0.1 gives ``s' = s + a``; reward +1
and done when ``s' . u_g > 0.5``, else 0 and not done.  The data keeps rows with
``s . u_g`` in [-0.5, 0.5] (before the line, at most ~10 moves from it), random
goals and random directions.  From ``s . u_g`` in [0, 0.45] the line is 1-5 moves
away; with ``d = (0.5 - s . u_g) / c = n + f`` (``0 < f <= 1``) the optimal actions
(those needing the fewest moves) are exactly the cone ``cos(a, u_g) >= f`` around
``u_g``, so a greedy argmax of a smooth Q and an advantage-weighted mean direction
both point along ``u_g``.  26 degrees is the reward's cone on the push task
(arccos 0.9 = 25.8 degrees).

Each learned method is compiled once (module fixture) and trained in one vmapped
program on two lanes: (key 0, dataset A, all rows) and (key 1, dataset B whose rows
>= 15,000 are NaN, n_valid = 15,000).  Lane 1 stays finite only if padding is never
sampled.  Determinism and the unbatched interface are checked on a tiny config.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lazyq_jax.baselines as bl
from lazyq_jax.config import ConfigError, EvalConfig
from lazyq_jax.evaluate import CORRECT, WRONG, protocol_a
from lazyq_jax.env.scripted import scripted_push_policy
from lazyq_jax.types import Transitions

C = 0.1
LINE = 0.5
N_ROWS = 20_000
N_VALID_B = 15_000
TOLERANCE_DEG = 26.0  # the push task's reward cone, arccos 0.9
LEARNED = ("iql", "td3bc", "dqn", "naf", "bc")

# Small networks and budgets that learn the synthetic task in seconds on 2 CPU cores
# (measured on two datasets: the fraction within 26 degrees, vs the 0.7 asserted).
SMALL = {"steps": 2000, "batch_size": 256, "width": 64, "depth": 3, "log_every": 100}
SMALL_OVERRIDES = {
    # tau 0.05 instead of 0.005: a 2000-step budget then spans ~100 target time
    # constants (value iteration needs >= 10 for the 10 moves of data); temperature 10:
    # advantages here are ~0.05 (one move costs a factor gamma on values ~0.5), so the
    # default beta = 3 weights the data almost uniformly (exp(0.15)) and the actor stays
    # close to the random behaviour (0.63-0.79 at beta 3; 0.97-0.98 at beta 10).
    "iql": {"tau": 0.05, "temperature": 10.0},
    "td3bc": {"tau": 0.05},  # 0.95 / 0.84 (0.73 / 0.82 at tau 0.005)
    # Greedy over Q needs the values nearly converged: 8000 cheap steps (one network).
    "dqn": {"tau": 0.05, "learning_rate": 1e-3, "steps": 8000},  # 0.84 / 0.89
    "naf": {"tau": 0.05, "learning_rate": 1e-3, "steps": 8000},  # 1.00 / 1.00 (0.5 at 4000)
    # ~600 positive rows: longer training overfits them (0.63 / 0.60 at 2000 steps).
    "bc": {"steps": 500},  # 0.96 / 0.82
}


def small_config(name, **extra):
    return bl.config_class(name)(**{**SMALL, **SMALL_OVERRIDES[name], **extra})


def synthetic(key, n):
    ks, kg, ka = jax.random.split(key, 3)
    s = jax.random.uniform(ks, (4 * n, 2), minval=-1.0, maxval=1.0)
    g = jax.random.uniform(kg, (4 * n,), minval=-jnp.pi, maxval=jnp.pi)
    proj = jnp.sum(s * jnp.stack([jnp.cos(g), jnp.sin(g)], -1), -1)
    # Only rows before the line and at most ~10 moves from it (s . u_g in [-0.5, 0.5];
    # about 60 % of the candidates, so 4 n are plenty).
    keep = jnp.nonzero(jnp.abs(proj) <= LINE, size=n)[0]
    s, g = s[keep], g[keep]
    theta = jax.random.uniform(ka, (n,), minval=-jnp.pi, maxval=jnp.pi)
    a = C * jnp.stack([jnp.cos(theta), jnp.sin(theta)], -1)
    s_next = s + a
    done = jnp.sum(s_next * jnp.stack([jnp.cos(g), jnp.sin(g)], -1), -1) > LINE
    return Transitions(s=s, a=a, s_next=s_next, r=done.astype(jnp.float32), g=g, done=done)


def probe_states(n=2000, seed=0):
    """States with ``s . u_g`` in [0, 0.45]: 1-5 moves from the line."""
    rng = np.random.default_rng(seed)
    s = rng.uniform(-1, 1, (8 * n, 2))
    g = rng.uniform(-np.pi, np.pi, 8 * n)
    proj = np.sum(s * np.stack([np.cos(g), np.sin(g)], 1), 1)
    keep = (proj >= 0) & (proj <= 0.45)
    return s[keep][:n].astype(np.float32), g[keep][:n].astype(np.float32)


def angle_errors_deg(actions, g):
    theta = np.arctan2(actions[:, 1], actions[:, 0])
    return np.degrees(np.abs(np.angle(np.exp(1j * (theta - g)))))


def lane(tree, i):
    return jax.tree.map(lambda x: x[i], tree)


@pytest.fixture(scope="module")
def datasets():
    a = synthetic(jax.random.PRNGKey(10), N_ROWS)
    b = synthetic(jax.random.PRNGKey(11), N_ROWS)
    nan_tail = lambda x: x.at[N_VALID_B:].set(jnp.nan) if x.dtype != bool else x
    b = jax.tree.map(nan_tail, b)
    stacked = jax.tree.map(lambda *xs: jnp.stack(xs), a, b)
    return a, stacked


@pytest.fixture(scope="module")
def trained(datasets):
    """``name -> (agent, states [2 lanes], metrics [2 lanes])``, trained on first use."""
    _, stacked = datasets
    keys = jnp.stack([jax.random.PRNGKey(0), jax.random.PRNGKey(1)])
    n_valid = jnp.array([N_ROWS, N_VALID_B], jnp.int32)
    cache = {}

    def get(name):
        if name not in cache:
            agent = bl.make(name, small_config(name), action_length=C)
            states, metrics = jax.jit(jax.vmap(agent.train))(keys, stacked, n_valid)
            cache[name] = (agent, jax.block_until_ready(states), metrics)
        return cache[name]

    return get


# ----------------------------------------------------------------------------- registry, configs


def test_registry_and_defaults():
    assert bl.METHODS == LEARNED
    for name in bl.METHODS:
        cfg = bl.config_class(name)()
        assert dataclasses.is_dataclass(cfg)
        assert (cfg.steps, cfg.batch_size, cfg.width, cfg.depth, cfg.gamma) == (24_200, 4096, 32,
                                                                                 9, 0.9)
        agent = bl.make(name)
        assert agent.name == name and agent.config == cfg and agent.action_length == 0.1
        with pytest.raises(dataclasses.FrozenInstanceError):
            cfg.steps = 3
    assert bl.config_class("iql")().expectile == 0.9 and bl.config_class("iql")().temperature == 3.0
    assert bl.config_class("td3bc")().alpha == 2.5 and bl.config_class("td3bc")().policy_freq == 2
    assert bl.config_class("dqn")().bins == 16 and bl.config_class("dqn")().cql_alpha == 0.0


def test_make_rejects_unknown_names_and_wrong_configs():
    with pytest.raises(ConfigError, match="known: iql, td3bc, dqn, naf, bc"):
        bl.make("sac")
    with pytest.raises(ConfigError, match="unknown baseline"):
        bl.config_class("sac")
    with pytest.raises(TypeError, match="IQLConfig"):
        bl.make("iql", bl.config_class("td3bc")())
    with pytest.raises(TypeError):
        bl.make("bc", {"steps": 3})
    with pytest.raises(ConfigError, match="action_length"):
        bl.make("naf", action_length=0.0)


@pytest.mark.parametrize("name, field, value, allowed", [
    ("iql", "steps", 0, ">= 1"),
    ("iql", "expectile", 1.0, "(0, 1)"),
    ("iql", "temperature", -1.0, "[0, inf]"),
    ("iql", "tau", 0.0, "(0, 1]"),
    ("td3bc", "alpha", float("nan"), "[0, inf]"),
    ("td3bc", "policy_freq", 0, ">= 1"),
    ("td3bc", "batch_size", 2.5, ">= 1"),
    ("dqn", "bins", 1, ">= 2"),
    ("dqn", "cql_alpha", -0.1, "[0, inf]"),
    ("dqn", "target_period", -1, ">= 0"),
    ("naf", "gamma", 1.0, "[0, 1)"),
    ("naf", "learning_rate", 0.0, "(0, inf]"),
    ("bc", "depth", 1, ">= 2"),
    ("bc", "width", True, ">= 1"),
])
def test_bad_configs_name_the_field_and_the_range(name, field, value, allowed):
    cls = bl.config_class(name)
    with pytest.raises(ConfigError) as err:
        cls(**{field: value})
    message = str(err.value)
    assert f"{cls.__name__}.{field}" in message and allowed in message, message


def test_random_policy_gives_random_directions_of_length_c():
    act = bl.random_policy(0.1)
    s, g = jnp.zeros((512, 2)), jnp.zeros(512)
    a1, a2 = np.asarray(act(jax.random.PRNGKey(0), s, g)), np.asarray(act(jax.random.PRNGKey(1), s, g))
    np.testing.assert_allclose(np.linalg.norm(a1, axis=1), 0.1, rtol=1e-5)
    assert not np.allclose(a1, a2)
    # roughly uniform: the mean direction of 512 unit vectors is ~ 1/sqrt(512) = 0.044 long
    assert np.linalg.norm(a1.mean(0) / 0.1) < 0.2


# ----------------------------------------------------------------------------- learning


@pytest.mark.parametrize("name", LEARNED)
def test_learns_the_optimal_direction(name, trained):
    agent, states, _ = trained(name)
    s, g = probe_states()
    for i in (0, 1):  # both datasets, both keys
        actions = np.asarray(agent.policy(lane(states, i))(jax.random.PRNGKey(5), s, g))
        err = angle_errors_deg(actions, g)
        # >= 70 %: the optimal set is a cone around u_g, often wider than 26 degrees (all
        # directions that need no extra move), and one extra move only costs a factor
        # gamma, so small value errors move a greedy action around inside that cone.
        assert np.mean(err < TOLERANCE_DEG) >= 0.7, (name, i, np.mean(err < TOLERANCE_DEG),
                                                     np.median(err))


@pytest.mark.parametrize("name", LEARNED)
def test_padding_is_never_sampled(name, trained):
    agent, states, metrics = trained(name)
    for leaf in jax.tree.leaves(lane(states, 1)) + jax.tree.leaves(lane(metrics, 1)):
        assert np.all(np.isfinite(np.asarray(leaf, np.float64))), name  # NaN rows >= n_valid
    n_log = agent.config.steps // agent.config.log_every
    for key, value in metrics.items():
        assert value.shape in ((2, n_log), (2,)), (key, value.shape)


TINY = {"steps": 4, "batch_size": 16, "width": 8, "depth": 2, "log_every": 2}


@pytest.fixture(scope="module")
def tiny(datasets):
    """``name -> (agent, jitted unbatched train, data[64])`` on a tiny config."""
    data = jax.tree.map(lambda x: x[:64], datasets[0])
    cache = {}

    def get(name):
        if name not in cache:
            agent = bl.make(name, bl.config_class(name)(**TINY), action_length=C)
            cache[name] = (agent, jax.jit(agent.train), data)
        return cache[name]

    return get


@pytest.mark.parametrize("name", LEARNED)
def test_unbatched_train_is_deterministic_and_actions_are_on_the_circle(name, tiny):
    agent, train, data = tiny(name)
    first, metrics = train(jax.random.PRNGKey(3), data)
    second, _ = train(jax.random.PRNGKey(3), data)
    other, _ = train(jax.random.PRNGKey(4), data)
    leaves = lambda t: [np.asarray(x) for x in jax.tree.leaves(t)]
    assert all(np.array_equal(x, y) for x, y in zip(leaves(first), leaves(second), strict=True))
    assert not all(np.array_equal(x, y) for x, y in zip(leaves(first), leaves(other), strict=True))
    for value in metrics.values():
        assert value.shape in ((2,), ()) and np.all(np.isfinite(value))
    s = jnp.concatenate([data.s[:7], jnp.zeros((1, 2))])  # includes s = 0
    g = jnp.concatenate([data.g[:7], jnp.array([np.pi])])
    a = np.asarray(agent.policy(first)(jax.random.PRNGKey(0), s, g))
    assert a.shape == (8, 2) and np.all(np.isfinite(a))
    np.testing.assert_allclose(np.linalg.norm(a, axis=1), C, rtol=1e-5)


def test_actions_stay_finite_for_degenerate_parameters(tiny):
    """All-zero (and NaN) network outputs still give length-c actions, never NaN."""
    for name in ("iql", "td3bc", "naf", "bc"):
        agent, train, data = tiny(name)
        state, _ = train(jax.random.PRNGKey(3), data)
        for fill in (0.0, np.nan):
            broken = jax.tree.map(lambda x, f=fill: jnp.full_like(x, f)
                                  if jnp.issubdtype(x.dtype, jnp.floating) else x, state)
            a = np.asarray(agent.policy(broken)(None, data.s[:4], data.g[:4]))
            np.testing.assert_allclose(np.linalg.norm(a, axis=1), C, rtol=1e-5)


def test_bc_without_positive_rows_keeps_its_initialisation(tiny, datasets):
    _, train, data = tiny("bc")
    # Two different datasets without a positive row (the second has positives, but only
    # at rows >= n_valid): with no update applied, both runs end at the same (initial)
    # parameters, while a run with positives moves away from them.
    unrewarded = data.replace(r=jnp.zeros_like(data.r), done=jnp.zeros_like(data.done))
    rewarded = jax.tree.map(lambda x: x[1000:1064], datasets[0])
    rewarded = rewarded.replace(r=jnp.zeros_like(rewarded.r).at[40:].set(1.0))
    key = jax.random.PRNGKey(0)
    n_valid = lambda n: jnp.int32(n)  # the same compiled function for all three
    a, metrics = train(key, unrewarded, n_valid(64))
    b, _ = train(key, rewarded, n_valid(40))
    c, _ = train(key, rewarded, n_valid(64))
    leaves = lambda t: [np.asarray(x) for x in jax.tree.leaves(t.params)]
    assert all(np.array_equal(x, y) for x, y in zip(leaves(a), leaves(b), strict=True))
    assert not all(np.array_equal(x, y) for x, y in zip(leaves(a), leaves(c), strict=True))
    assert int(metrics["positives"]) == 0
    assert np.all(np.asarray(metrics["loss"]) == 0)



# ----------------------------------------------------------------------------- scripted controller


def test_scripted_controller_pushes_toward_axis_goals(env):
    """Protocol A (Fig. 4) in the paper's world: 4 axis goals x 4 starts behind the disk
    (up to 1.0 away), at most 15 moves; CORRECT when the first move of the disk is
    within arccos 0.9 of the goal.  The controller never touches the disk before it is
    behind it and needs at most ~12 moves from such starts (the path around the disk
    included), so every episode should be correct; >= 14 / 16 leaves room for physics."""
    act = scripted_push_policy(env.config)
    cfg = EvalConfig(n_directions=4, episodes_per_direction=4, max_steps=15, start_range=1.0)
    rollouts = jax.jit(lambda key: protocol_a(
        env, lambda k, s, g: (act(k, s, g), jnp.ones(s.shape[0], bool)), key, cfg))(
        jax.random.PRNGKey(7))
    outcome = np.asarray(rollouts.outcome)
    assert np.sum(outcome == CORRECT) >= 14, outcome
    assert np.sum(outcome == WRONG) <= 1, outcome
