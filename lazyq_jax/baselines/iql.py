"""Goal-conditioned Implicit Q-Learning.

Kostrikov, Nair & Levine, "Offline Reinforcement Learning with Implicit Q-Learning",
ICLR 2022 (arXiv:2110.06169), goal-conditioned as OGBench's ``gciql`` (Park et al.
2024).  Per step, on one minibatch, all three losses (one Adam over all parameters):

* value, expectile regression (IQL Eq. 5) on the target critics:
  ``L_V = E[|tau - 1(d < 0)| d^2]``, ``d = min(Q1_t, Q2_t)(s, a, g) - V(s, g)``,
  ``tau = expectile`` (0.9);
* critics (IQL Eq. 6): ``L_Q = sum_i E[(Q_i(s, a, g) - r - gamma (1 - done) V(s', g))^2]``
  (``V(s')`` not differentiated);
* actor, advantage-weighted regression (IQL Eq. 7):
  ``L_pi = -E[min(exp(beta (Q_t - V)), 100) log pi(a | s, g)]``, ``beta = temperature`` (3).

Target critics follow the critics by Polyak averaging (``tau`` 0.005).

The actor is a von Mises distribution over the action angle (actions lie on the
circle of radius ``c``): ``log pi(a) = kappa cos(theta_a - theta_mu) - log(2 pi I0(kappa))``
with mean direction ``mu = u / |u|``, ``u`` = the network's two outputs.  ``kappa`` is
fixed at 1: for any fixed ``kappa > 0`` the weighted likelihood is maximised by the
same ``mu`` (``kappa`` only scales the loss, which Adam undoes), and a learned
``kappa`` would leave ``mu`` unchanged too, since evaluation acts with ``mu``.  So the
actor loss is ``-E[w cos(a, mu)]``.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import jax
import jax.numpy as jnp
import optax
from flax import struct

from lazyq_jax.baselines.common import (Agent, BaselineConfig, apply_ensemble, check_range,
                                        fit, init_ensemble, mask_of, mlp, observe,
                                        observe_action, on_circle, polyak, unit)
from lazyq_jax.types import Transitions


@dataclasses.dataclass(frozen=True)
class IQLConfig(BaselineConfig):
    """:class:`BaselineConfig` plus ``tau`` (Polyak rate of the target critics),
    ``expectile`` (of the value regression), ``temperature`` (AWR ``beta``) and
    ``max_weight`` (cap of the AWR weights)."""

    tau: float = 0.005
    expectile: float = 0.9
    temperature: float = 3.0
    max_weight: float = 100.0

    def __post_init__(self) -> None:
        super().__post_init__()
        check_range(self, "tau", 0.0, 1.0, lo_open=True)
        check_range(self, "expectile", 0.0, 1.0, lo_open=True, hi_open=True)
        check_range(self, "temperature", 0.0, math.inf)
        check_range(self, "max_weight", 0.0, math.inf, lo_open=True)


@struct.dataclass
class IQLState:
    params: Any  # {"value": V, "critic": two stacked Q, "actor": pi}
    target_critic: Any
    opt_state: Any
    step: jax.Array


def make(config: IQLConfig, action_length: float, progress=None) -> Agent:
    c = action_length
    value_net, critic_net, actor_net = mlp(config, 1), mlp(config, 1), mlp(config, 2)
    optimizer = optax.adam(config.learning_rate)

    def init(key):
        kv, kq, kp = jax.random.split(key, 3)
        x, xa = jnp.zeros((1, 4)), jnp.zeros((1, 6))
        params = {"value": value_net.init(kv, x), "critic": init_ensemble(critic_net, kq, xa),
                  "actor": actor_net.init(kp, x)}
        return IQLState(params=params, target_critic=params["critic"],
                        opt_state=optimizer.init(params), step=jnp.int32(0))

    def loss_fn(params, target_critic, b: Transitions):
        x = observe(config, b.s, b.g)
        xa = observe_action(config, b.s, b.g, b.a, c)
        q_t = jnp.min(apply_ensemble(critic_net, target_critic, xa)[..., 0], axis=0)
        v = value_net.apply(params["value"], x)[:, 0]
        d = q_t - v
        value_loss = jnp.mean(jnp.where(d < 0, 1.0 - config.expectile, config.expectile) * d ** 2)

        v_next = jax.lax.stop_gradient(value_net.apply(params["value"],
                                                       observe(config, b.s_next, b.g))[:, 0])
        y = b.r + config.gamma * mask_of(b) * v_next
        q = apply_ensemble(critic_net, params["critic"], xa)[..., 0]  # [2, B]
        critic_loss = jnp.sum(jnp.mean((q - y) ** 2, axis=1))

        adv = q_t - jax.lax.stop_gradient(v)
        weight = jnp.minimum(jnp.exp(config.temperature * adv), config.max_weight)
        mu = unit(actor_net.apply(params["actor"], x))
        log_prob = jnp.sum(mu * unit(b.a), axis=-1)  # kappa cos(theta_a - theta_mu), kappa = 1
        actor_loss = -jnp.mean(weight * log_prob)
        metrics = {"value_loss": value_loss, "critic_loss": critic_loss,
                   "actor_loss": actor_loss, "q_mean": jnp.mean(q_t),
                   "weight_mean": jnp.mean(weight)}
        return value_loss + critic_loss + actor_loss, metrics

    def update(state: IQLState, batch: Transitions, key, step):
        grads, metrics = jax.grad(loss_fn, has_aux=True)(state.params, state.target_critic, batch)
        updates, opt_state = optimizer.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        state = IQLState(params=params, target_critic=polyak(state.target_critic,
                                                             params["critic"], config.tau),
                         opt_state=opt_state, step=state.step + 1)
        return state, metrics

    def train(key, data: Transitions, n_valid=None):
        return fit(config, init, update, key, data, n_valid, progress=progress)

    def policy(state: IQLState):
        def act(key, s, g):
            return on_circle(actor_net.apply(state.params["actor"], observe(config, s, g)), c)

        return act

    return Agent("iql", config, c, train, policy)
