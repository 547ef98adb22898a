"""Double DQN over direction bins, with an optional discrete CQL(H) penalty.

Double DQN: van Hasselt, Guez & Silver, "Deep Reinforcement Learning with Double
Q-learning", AAAI 2016 (on Mnih et al., Nature 2015).  CQL(H): Kumar, Zhou, Tucker &
Levine, "Conservative Q-Learning for Offline Reinforcement Learning", NeurIPS 2020,
Eq. 4 (the discrete-action form of its published code).

The action circle is cut into ``K = bins`` directions ``theta_k = 2 pi k / K``; a
dataset action counts as its nearest bin (binning error at most ``pi / K``, 11.25
degrees at the default 16, well inside the reward's cone of arccos 0.9 = 25.8
degrees).  The network outputs ``Q(s, g, k)`` for all ``K`` bins.

* Loss: ``E[(Q(s, g, k_a) - y)^2] + cql_alpha E[logsumexp_k Q(s, g, k) - Q(s, g, k_a)]``
  with the Double DQN target ``y = r + gamma (1 - done) Q_t(s', g, argmax_k Q(s', g, k))``.
  Squared error (as lazy Q's Eq. 10), not Huber: rewards are in {-1, 0, 1}, so the
  TD errors are bounded and Huber's outlier robustness buys nothing.
* Target network: Polyak averaging (``tau`` 0.005), or a hard copy every
  ``target_period`` steps when ``target_period > 0``.
* Policy: ``c (cos theta_k*, sin theta_k*)`` of the greedy bin.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import jax
import jax.numpy as jnp
import optax
from flax import struct

from lazyq_jax.baselines.common import (Agent, BaselineConfig, angle_action, check_int,
                                        check_range, fit, mask_of, mlp, observe, polyak, select)
from lazyq_jax.types import Transitions


@dataclasses.dataclass(frozen=True)
class DQNConfig(BaselineConfig):
    """:class:`BaselineConfig` plus ``bins`` (directions), ``cql_alpha`` (CQL(H) weight, 0 =
    plain Double DQN), ``tau`` (Polyak rate) and ``target_period`` (> 0: hard target
    copies every that many steps instead of Polyak averaging)."""

    bins: int = 16
    cql_alpha: float = 0.0
    tau: float = 0.005
    target_period: int = 0

    def __post_init__(self) -> None:
        super().__post_init__()
        check_int(self, "bins", 2)
        check_range(self, "cql_alpha", 0.0, math.inf)
        check_range(self, "tau", 0.0, 1.0, lo_open=True)
        check_int(self, "target_period", 0)


@struct.dataclass
class DQNState:
    params: Any
    target: Any
    opt_state: Any
    step: jax.Array


def nearest_bin(a: jax.Array, bins: int) -> jax.Array:
    """Index of the bin ``theta_k = 2 pi k / K`` nearest to the direction of ``a[..., 2]``."""
    k = jnp.round(jnp.arctan2(a[..., 1], a[..., 0]) * (bins / (2 * jnp.pi))).astype(jnp.int32)
    return jnp.mod(k, bins)


def make(config: DQNConfig, action_length: float, progress=None) -> Agent:
    c, k_bins = action_length, config.bins
    net = mlp(config, k_bins)
    optimizer = optax.adam(config.learning_rate)
    angles = 2 * jnp.pi * jnp.arange(k_bins, dtype=jnp.float32) / k_bins

    def q_all(params, s, g):
        return net.apply(params, observe(config, s, g))  # [B, K]

    def init(key):
        params = net.init(key, jnp.zeros((1, 4)))
        return DQNState(params=params, target=params, opt_state=optimizer.init(params),
                        step=jnp.int32(0))

    def loss_fn(params, target, b: Transitions):
        k_data = nearest_bin(b.a, k_bins)
        greedy = jnp.argmax(q_all(params, b.s_next, b.g), axis=-1)
        q_next = jnp.take_along_axis(q_all(target, b.s_next, b.g), greedy[:, None], axis=-1)[:, 0]
        y = jax.lax.stop_gradient(b.r + config.gamma * mask_of(b) * q_next)
        q = q_all(params, b.s, b.g)
        q_data = jnp.take_along_axis(q, k_data[:, None], axis=-1)[:, 0]
        td = jnp.mean((q_data - y) ** 2)
        cql = jnp.mean(jax.nn.logsumexp(q, axis=-1) - q_data)
        return td + config.cql_alpha * cql, {"td_loss": td, "cql_gap": cql,
                                             "q_mean": jnp.mean(q_data)}

    def update(state: DQNState, b: Transitions, key, step):
        grads, metrics = jax.grad(loss_fn, has_aux=True)(state.params, state.target, b)
        updates, opt_state = optimizer.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        if config.target_period > 0:
            target = select((step + 1) % config.target_period == 0, params, state.target)
        else:
            target = polyak(state.target, params, config.tau)
        return DQNState(params=params, target=target, opt_state=opt_state,
                        step=state.step + 1), metrics

    def train(key, data: Transitions, n_valid=None):
        return fit(config, init, update, key, data, n_valid, progress=progress)

    def policy(state: DQNState):
        def act(key, s, g):
            return angle_action(angles[jnp.argmax(q_all(state.params, s, g), axis=-1)], c)

        return act

    return Agent("dqn", config, c, train, policy)
