"""TD3+BC.

Fujimoto & Gu, "A Minimalist Approach to Offline Reinforcement Learning", NeurIPS
2021 (arXiv:2106.06860), on TD3 (Fujimoto, van Hoof & Meger, ICML 2018).

* Deterministic actor on the action circle: ``pi(s, g) = c u / |u|``.
* Critics (TD3): ``L_Q = sum_i E[(Q_i(s, a, g) - y)^2]``,
  ``y = r + gamma (1 - done) min_i Q_i,t(s', a', g)`` with target policy smoothing
  ``a' = c normalize(pi_t(s', g) + clip(eps, -noise_clip c, noise_clip c))``,
  ``eps ~ N(0, (policy_noise c)^2)`` per component (0.2 c clipped at 0.5 c), projected
  back onto the circle (the only feasible actions).
* Actor every ``policy_freq`` (2) steps, TD3+BC Eq. 3:
  ``L_pi = -lambda E[Q1(s, pi(s, g), g)] + E[|pi(s, g) - a|^2] / c^2`` with
  ``lambda = alpha / E|Q1(s, pi(s, g), g)|`` (not differentiated), ``alpha`` 2.5; the
  behaviour term is in action units ``a / c``.  Target actor and critics follow by
  Polyak averaging (``tau`` 0.005) on the same steps, as in the authors' code.

The paper's state normalisation is replaced by the shared input encoding (states
divided by ``state_scale``, goals as ``cos g, sin g``).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import jax
import jax.numpy as jnp
import optax
from flax import struct

from lazyq_jax.baselines.common import (Agent, BaselineConfig, apply_ensemble, check_int,
                                        check_range, fit, init_ensemble, mask_of, mlp,
                                        observe, observe_action, on_circle, polyak, select)
from lazyq_jax.types import Transitions


@dataclasses.dataclass(frozen=True)
class TD3BCConfig(BaselineConfig):
    """:class:`BaselineConfig` plus ``tau`` (Polyak rate), ``alpha`` (weight of the Q term),
    ``policy_noise`` and ``noise_clip`` (target smoothing, in units of ``c``) and
    ``policy_freq`` (critic steps per actor step)."""

    tau: float = 0.005
    alpha: float = 2.5
    policy_noise: float = 0.2
    noise_clip: float = 0.5
    policy_freq: int = 2

    def __post_init__(self) -> None:
        super().__post_init__()
        check_range(self, "tau", 0.0, 1.0, lo_open=True)
        check_range(self, "alpha", 0.0, math.inf)
        check_range(self, "policy_noise", 0.0, math.inf)
        check_range(self, "noise_clip", 0.0, math.inf)
        check_int(self, "policy_freq", 1)


@struct.dataclass
class TD3BCState:
    critic: Any  # two stacked Q
    actor: Any
    target_critic: Any
    target_actor: Any
    critic_opt: Any
    actor_opt: Any
    step: jax.Array


def make(config: TD3BCConfig, action_length: float, progress=None) -> Agent:
    c = action_length
    critic_net, actor_net = mlp(config, 1), mlp(config, 2)
    critic_optimizer = optax.adam(config.learning_rate)
    actor_optimizer = optax.adam(config.learning_rate)

    def pi(actor, s, g):
        return on_circle(actor_net.apply(actor, observe(config, s, g)), c)

    def q_values(critic, s, g, a):
        return apply_ensemble(critic_net, critic, observe_action(config, s, g, a, c))[..., 0]

    def init(key):
        kq, kp = jax.random.split(key)
        critic = init_ensemble(critic_net, kq, jnp.zeros((1, 6)))
        actor = actor_net.init(kp, jnp.zeros((1, 4)))
        return TD3BCState(critic=critic, actor=actor, target_critic=critic, target_actor=actor,
                          critic_opt=critic_optimizer.init(critic),
                          actor_opt=actor_optimizer.init(actor), step=jnp.int32(0))

    def critic_loss(critic, state: TD3BCState, b: Transitions, key):
        noise = jnp.clip(config.policy_noise * c * jax.random.normal(key, b.a.shape),
                         -config.noise_clip * c, config.noise_clip * c)
        a_next = on_circle(pi(state.target_actor, b.s_next, b.g) + noise, c)
        q_next = jnp.min(q_values(state.target_critic, b.s_next, b.g, a_next), axis=0)
        y = jax.lax.stop_gradient(b.r + config.gamma * mask_of(b) * q_next)
        q = q_values(critic, b.s, b.g, b.a)
        return jnp.sum(jnp.mean((q - y) ** 2, axis=1)), jnp.mean(q)

    def actor_loss(actor, critic, b: Transitions):
        action = pi(actor, b.s, b.g)
        q1 = q_values(member_first(critic), b.s, b.g, action)[0]
        lam = config.alpha / jnp.maximum(jax.lax.stop_gradient(jnp.mean(jnp.abs(q1))), 1e-6)
        bc = jnp.mean(jnp.sum((action - b.a) ** 2, axis=-1)) / c ** 2
        return -lam * jnp.mean(q1) + bc, bc

    def member_first(critic):  # Q1 as a one-member ensemble
        return jax.tree.map(lambda p: p[:1], critic)

    def update(state: TD3BCState, b: Transitions, key, step):
        (q_loss, q_mean), grads = jax.value_and_grad(critic_loss, has_aux=True)(
            state.critic, state, b, key)
        updates, critic_opt = critic_optimizer.update(grads, state.critic_opt, state.critic)
        critic = optax.apply_updates(state.critic, updates)

        (p_loss, bc), grads = jax.value_and_grad(actor_loss, has_aux=True)(state.actor, critic, b)
        updates, actor_opt = actor_optimizer.update(grads, state.actor_opt, state.actor)
        actor = optax.apply_updates(state.actor, updates)
        # Delayed policy updates: computed every step (vmap turns a cond into a select
        # anyway), kept every policy_freq-th step.
        delayed = (step % config.policy_freq) == 0
        actor, actor_opt = select(delayed, (actor, actor_opt), (state.actor, state.actor_opt))
        targets = select(delayed, (polyak(state.target_critic, critic, config.tau),
                                   polyak(state.target_actor, actor, config.tau)),
                         (state.target_critic, state.target_actor))
        state = TD3BCState(critic=critic, actor=actor, target_critic=targets[0],
                           target_actor=targets[1], critic_opt=critic_opt, actor_opt=actor_opt,
                           step=state.step + 1)
        return state, {"critic_loss": q_loss, "actor_loss": p_loss, "bc_loss": bc,
                       "q_mean": q_mean}

    def train(key, data: Transitions, n_valid=None):
        return fit(config, init, update, key, data, n_valid, progress=progress)

    def policy(state: TD3BCState):
        return lambda key, s, g: pi(state.actor, s, g)

    return Agent("td3bc", config, c, train, policy)
