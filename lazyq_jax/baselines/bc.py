"""Filtered behaviour cloning: imitate only the transitions that earned r = +1.

"%BC" / filtered BC as in Chen et al., "Decision Transformer", NeurIPS 2021 (§5) and
Emmons et al., "RvS: What is Essential for Offline RL via Supervised Learning?",
ICLR 2022: behaviour cloning on the best part of the data, here the rows with
``r > 0`` (a correct push, Eq. 15).

Deterministic actor ``pi(s, g) = c u / |u|``; loss ``-E[cos(u, a)]`` over positive rows
(maximum likelihood of a von Mises policy with fixed concentration, as the IQL actor
with unit weights), each minibatch drawn uniformly with replacement among the
positive rows ``< n_valid``.  A dataset without a positive row leaves the actor at
its initialisation (no update is applied) and reports ``positives = 0``.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import optax
from flax import struct

from lazyq_jax.baselines.common import (Agent, BaselineConfig, fit, mlp, observe, on_circle,
                                        select, unit, valid_rows)
from lazyq_jax.types import Transitions


@dataclasses.dataclass(frozen=True)
class BCConfig(BaselineConfig):
    """:class:`BaselineConfig` (``gamma`` is unused)."""


@struct.dataclass
class BCState:
    params: Any
    opt_state: Any
    step: jax.Array


def make(config: BCConfig, action_length: float, progress=None) -> Agent:
    c = action_length
    net = mlp(config, 2)
    optimizer = optax.adam(config.learning_rate)

    def init(key):
        params = net.init(key, jnp.zeros((1, 4)))
        return BCState(params=params, opt_state=optimizer.init(params), step=jnp.int32(0))

    def loss_fn(params, b: Transitions):
        direction = unit(net.apply(params, observe(config, b.s, b.g)))
        cos = jnp.sum(direction * unit(b.a), axis=-1)
        return -jnp.mean(cos), jnp.mean(cos)

    def train(key, data: Transitions, n_valid=None):
        n = data.r.shape[0]
        n_valid = valid_rows(data, n_valid)
        positive = (jnp.arange(n) < n_valid) & (data.r > 0)
        count = jnp.sum(positive, dtype=jnp.int32)
        rows = jnp.nonzero(positive, size=n, fill_value=0)[0]
        has_data = count > 0

        def draw(k):
            return rows[jax.random.randint(k, (config.batch_size,), 0, jnp.maximum(count, 1))]

        def update(state: BCState, b: Transitions, key, step):
            (loss, cos), grads = jax.value_and_grad(loss_fn, has_aux=True)(state.params, b)
            updates, opt_state = optimizer.update(grads, state.opt_state, state.params)
            new = BCState(params=optax.apply_updates(state.params, updates), opt_state=opt_state,
                          step=state.step + 1)
            zero = jnp.zeros_like(loss)
            return select(has_data, new, state), {"loss": jnp.where(has_data, loss, zero),
                                                  "cos_mean": jnp.where(has_data, cos, zero)}

        state, metrics = fit(config, init, update, key, data, n_valid, draw=draw, progress=progress)
        return state, {**metrics, "positives": count}

    def policy(state: BCState):
        return lambda key, s, g: on_circle(net.apply(state.params, observe(config, s, g)), c)

    return Agent("bc", config, c, train, policy)
