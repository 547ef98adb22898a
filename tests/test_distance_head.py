"""``train.value_head="distance"``: the network's last layer counts the steps to the goal and V
follows from it.  The two maps against the discounted sum in NumPy, the Bellman step as one
more step, the cap, the network's two outputs, the cycle's loss against a NumPy reference in
distance units (with the expectile's weights on the right side), and the refusals."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_value_ablations import random_rows

from lazyq_jax.agents.base import Problem
from lazyq_jax.agents.lazy import LazyAgent, LazyConfig
from lazyq_jax.config import ConfigError, NeighbourConfig, TrainConfig
from lazyq_jax.networks import DISTANCE_CAP, ValueNetwork, distance_to_value, value_to_distance
from lazyq_jax.train import make_train

EPS32 = float(np.finfo(np.float32).eps)


def discounted_steps(d: np.ndarray, gamma: float) -> np.ndarray:
    """``-sum_{t < d} gamma^t`` in float64, by summing: -1 a step for ``d`` steps."""
    return -np.array([np.sum(gamma ** np.arange(k)) for k in d])


def inverse_tolerance(v: np.ndarray, d: np.ndarray, gamma: float) -> np.ndarray:
    """Steps of error in ``d(V)`` from V's float32 rounding: ``1 + (1 - gamma) V = gamma^d``
    carries an absolute error of a few ``eps |(1 - gamma) V|``, which ``log`` divides by
    ``gamma^d`` and ``|log gamma|`` (the loss of precision far from the goal that the cap
    bounds), plus a few ulps of d itself."""
    return 4 * EPS32 * ((1 - gamma) * np.abs(v) + 1) / (gamma ** d * abs(math.log(gamma))) + 4 * EPS32 * d


@pytest.mark.parametrize("gamma", [0.99, 0.995])
def test_the_maps_are_the_discounted_sum_and_its_inverse(gamma):
    d = np.arange(0, 900)
    want = discounted_steps(d, gamma)
    v = np.asarray(distance_to_value(jnp.asarray(d * (1 - gamma), jnp.float32), gamma), np.float64)
    # expm1 and a product in float32: a few ulps of |V| <= 1 / (1 - gamma)
    np.testing.assert_allclose(v, want, rtol=8 * EPS32, atol=8 * EPS32)
    u, capped = value_to_distance(jnp.asarray(want, jnp.float32), gamma)
    got = np.asarray(u, np.float64) / (1 - gamma)
    assert not np.any(np.asarray(capped))
    assert np.all(np.abs(got - d) <= inverse_tolerance(want, d, gamma)), np.max(np.abs(got - d))
    # the Bellman step of a -1 reward: Y = -1 + gamma V(d) is d + 1 steps
    y = -1.0 + gamma * distance_to_value(jnp.asarray(d * (1 - gamma), jnp.float32), gamma)
    got = np.asarray(value_to_distance(y, gamma)[0], np.float64) / (1 - gamma)
    assert np.all(np.abs(got - (d + 1)) <= 2 * inverse_tolerance(want, d + 1, gamma))


def test_the_cap_and_values_above_zero():
    gamma = 0.99
    u, capped = value_to_distance(jnp.asarray([-1 / (1 - gamma), -1e6, 0.0, 0.5]), gamma)
    np.testing.assert_allclose(np.asarray(u[:2]), DISTANCE_CAP, rtol=1e-5)
    assert np.asarray(capped).tolist() == [True, True, False, False]
    assert float(u[2]) == 0.0 and float(u[3]) < 0.0  # above V's maximum: a negative distance
    # V never exceeds 0, also where the head is below 0
    assert float(distance_to_value(jnp.float32(-0.3), gamma)) == 0.0


def test_the_network_returns_v_or_its_distance_head():
    data = random_rows(32, seed=3)
    net = ValueNetwork(width=8, depth=3, distance_gamma=0.99, output_init=2.0)
    variables = net.init(jax.random.PRNGKey(0), data.s[:1], data.g[:1])
    head = net.apply(variables, data.s, data.g, distance=True)
    np.testing.assert_array_equal(np.asarray(net.apply(variables, data.s, data.g)),
                                  np.asarray(distance_to_value(head, 0.99)))
    # output_init sets the head's bias: at init every row is ~2 horizons away
    assert float(variables["params"]["Dense_2"]["bias"][0]) == 2.0
    with pytest.raises(ValueError, match="distance=True needs a distance head"):
        ValueNetwork(width=8, depth=3).apply(variables, data.s, data.g, distance=True)


@pytest.mark.parametrize("tau", [0.5, 0.9])
def test_the_cycle_regresses_the_head_on_the_targets_distances(tau):
    """One cycle of ``target_max="next"`` (each row's one-step target ``Y = r + gamma (1 -
    done) V(s')``), one minibatch of all rows: the loss before the step is ``mean(w (u -
    u(Y))^2)`` of the head in training mode, with ``u(Y)`` from NumPy in float64 and (tau
    0.9) the expectile's weight ``tau`` where the target's value is at or above V, i.e. where ``u(Y) <=
    u``.  A loss of V against Y, or of u with the weights the wrong way round, differs by far."""
    gamma, n = 0.99, 256
    data = random_rows(n, seed=4)
    data = data.replace(r=data.r - 1.0)  # OGBench's rewards: 0 at the goal, else -1
    cfg = TrainConfig(target_max="next", value_head="distance", loss_expectile=tau, cycles=1, epochs=1,
                      width=8, depth=3, batch_size=n, gamma=gamma, value_init=-40.0)
    trainer = make_train(cfg, 0.1, action_set="box")
    state = trainer.init(jax.random.PRNGKey(0), data)
    v_next = np.asarray(trainer.value_fn(state)(data.s_next, data.g), np.float64)
    y = np.asarray(data.r, np.float64) + gamma * np.where(np.asarray(data.done), 0.0, v_next)
    u_y = (1 - gamma) * np.log1p((1 - gamma) * y) / math.log(gamma)
    variables = {"params": state.params, "batch_stats": state.batch_stats}
    head, _ = trainer.network.apply(variables, data.s, data.g, train=True, distance=True,
                                    mutable=["batch_stats"])
    head = np.asarray(head, np.float64)
    weight = 1.0 if tau == 0.5 else np.where(u_y <= head, tau, 1 - tau)  # 0.5: Eq. (10)
    want = np.mean(weight * (head - u_y) ** 2)
    _, metrics = jax.jit(trainer.run_cycle)(state, data, jnp.zeros((n, 4), jnp.int32))
    # float32 sums of 256 squares of magnitude ~0.1-1: a few 1e-6 relative
    np.testing.assert_allclose(float(metrics["loss_first_epoch"]), want, rtol=1e-4)
    assert float(metrics["distance_capped_fraction"]) == 0.0
    if tau != 0.5:
        flipped = np.mean(np.where(u_y <= head, 1 - tau, tau) * (head - u_y) ** 2)
        assert abs(flipped - want) > 1e-2 * want, (flipped, want)


def test_refusals():
    with pytest.raises(ConfigError, match="value_head must be 'value'.*or 'distance'"):
        TrainConfig(value_head="steps")
    data = random_rows(64, seed=5)  # rewards in {0, 1}: not -1 a step
    problem = Problem(action_length=0.1, action_set="box")
    agent = LazyAgent(LazyConfig(TrainConfig(value_head="distance"), NeighbourConfig(k=4)), problem)
    with pytest.raises(ConfigError, match=r"rewards must lie in \[-1, 0\]; these lie in \[0, 1\]"):
        agent.check_value_head(data, 64)
    agent.check_value_head(data.replace(r=data.r - 1.0), 64)  # OGBench's: accepted
