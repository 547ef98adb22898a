"""Normalized Advantage Functions, with the maximiser on the action circle.

Gu, Lillicrap, Sutskever & Levine, "Continuous Deep Q-Learning with Model-based
Acceleration", ICML 2016 (arXiv:1603.00748; the lazy-Q paper's ref. [11]), Eq. 3:

    Q(s, a, g) = V(s, g) - 1/2 (a' - mu)^T P (a' - mu),   P = L L^T,

with ``a' = a / c`` (action units, for conditioning), ``L`` lower triangular 2 x 2
with exponentiated diagonal (log-diagonal clipped to [-8, 8] against overflow) and
``mu = u / |u|`` ON the unit circle.  Actions are the circle ``|a| = c``; with ``mu`` on
it, ``max_{|a| = c} Q = Q(mu) = V`` exactly, so the target
``y = r + gamma (1 - done) V_t(s', g)`` bootstraps from a feasible action.  (Textbook
NAF, with ``mu`` unconstrained, bootstraps from ``V = Q(mu)`` at a point inside the
circle that no action reaches; in a trial its values inflated away from terminal
states and the policy pointed backwards: see DESIGN.md, "Facts for the baselines".)

Loss ``E[(Q(s, a, g) - y)^2]``; the target network follows by Polyak averaging
(``tau`` 0.005); the policy is ``c mu``.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import optax
from flax import struct

from lazyq_jax.baselines.common import (Agent, BaselineConfig, check_range, fit, mask_of, mlp,
                                        observe, on_circle, polyak, unit)
from lazyq_jax.types import Transitions

LOG_DIAG_CLIP = 8.0


@dataclasses.dataclass(frozen=True)
class NAFConfig(BaselineConfig):
    """:class:`BaselineConfig` plus ``tau`` (Polyak rate of the target network)."""

    tau: float = 0.005

    def __post_init__(self) -> None:
        super().__post_init__()
        check_range(self, "tau", 0.0, 1.0, lo_open=True)


@struct.dataclass
class NAFState:
    params: Any
    target: Any
    opt_state: Any
    step: jax.Array


def make(config: NAFConfig, action_length: float, progress=None) -> Agent:
    c = action_length
    net = mlp(config, 6)  # V, u (2), log L11, L21, log L22
    optimizer = optax.adam(config.learning_rate)

    def heads(params, s, g):
        out = net.apply(params, observe(config, s, g))
        return out[:, 0], unit(out[:, 1:3]), out[:, 3:6]

    def q_value(params, s, g, a):
        v, mu, l = heads(params, s, g)
        d = jnp.asarray(a, jnp.float32) / c - mu
        l11 = jnp.exp(jnp.clip(l[:, 0], -LOG_DIAG_CLIP, LOG_DIAG_CLIP))
        l22 = jnp.exp(jnp.clip(l[:, 2], -LOG_DIAG_CLIP, LOG_DIAG_CLIP))
        # (a' - mu)^T L L^T (a' - mu) = |L^T (a' - mu)|^2
        lt_d = jnp.stack([l11 * d[:, 0] + l[:, 1] * d[:, 1], l22 * d[:, 1]], axis=-1)
        advantage = -0.5 * jnp.sum(lt_d ** 2, axis=-1)
        return v + advantage, v, advantage

    def init(key):
        params = net.init(key, jnp.zeros((1, 4)))
        return NAFState(params=params, target=params, opt_state=optimizer.init(params),
                        step=jnp.int32(0))

    def loss_fn(params, target, b: Transitions):
        v_next = heads(target, b.s_next, b.g)[0]
        y = jax.lax.stop_gradient(b.r + config.gamma * mask_of(b) * v_next)
        q, v, adv = q_value(params, b.s, b.g, b.a)
        loss = jnp.mean((q - y) ** 2)
        return loss, {"loss": loss, "v_mean": jnp.mean(v), "advantage_mean": jnp.mean(adv)}

    def update(state: NAFState, b: Transitions, key, step):
        grads, metrics = jax.grad(loss_fn, has_aux=True)(state.params, state.target, b)
        updates, opt_state = optimizer.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        return NAFState(params=params, target=polyak(state.target, params, config.tau),
                        opt_state=opt_state, step=state.step + 1), metrics

    def train(key, data: Transitions, n_valid=None):
        return fit(config, init, update, key, data, n_valid, progress=progress)

    def policy(state: NAFState):
        return lambda key, s, g: on_circle(heads(state.params, s, g)[1], c)

    return Agent("naf", config, c, train, policy)
