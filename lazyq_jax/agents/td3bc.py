"""TD3+BC.

Fujimoto & Gu, "A Minimalist Approach to Offline Reinforcement Learning", NeurIPS
2021 (arXiv:2106.06860), on TD3 (Fujimoto, van Hoof & Meger, ICML 2018).

* Deterministic actor in the action set: ``pi(s, g) = c u / |u|`` (ball) or ``c tanh(u)``
  (box), ``u`` the network's ``n_a`` outputs.
* Critics (TD3): ``L_Q = sum_i E[(Q_i(s, a, g) - y)^2]``,
  ``y = r + gamma (1 - done) min_i Q_i,t(s', a', g)`` with target policy smoothing
  ``a' = project(pi_t(s', g) + clip(eps, -noise_clip c, noise_clip c))``,
  ``eps ~ N(0, (policy_noise c)^2)`` per component (0.2 c clipped at 0.5 c), projected
  back onto the action set (the sphere ``|a| = c``, or the box by clipping: the
  feasible actions).
* Actor every ``policy_freq`` (2) steps, TD3+BC Eq. 3:
  ``L_pi = -lambda E[Q1(s, pi(s, g), g)] + E[|pi(s, g) - a|^2] / c^2`` with
  ``lambda = alpha / E|Q1(s, pi(s, g), g)|`` (not differentiated), ``alpha`` 2.5; the
  behaviour term is in action units ``a / c``.  Target actor and critics follow by
  Polyak averaging (``tau`` 0.005) on the same steps, as in the authors' code.

The paper's state normalisation is replaced by the shared input encoding (states
divided by ``problem.state_scale``; goals as ``cos g, sin g``, a vector, or nothing).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import jax
import jax.numpy as jnp
import optax

from lazyq_jax.agents.base import Problem, Spec
from lazyq_jax.agents.common import (Baseline, BaselineConfig, apply_ensemble, apply_mlp, check_int,
                                     check_range, init_ensemble, mask_of, mlp, observe,
                                     observe_action, polyak, project, select, squash)
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


class TD3BC(Baseline):
    name = "td3bc"
    config_class = TD3BCConfig

    def __init__(self, config=None, problem=None, progress=None):
        super().__init__(config, problem, progress)
        self.critic_net = mlp(self.config, 1)
        self.optimizer = optax.adam(self.config.learning_rate)  # one per network

    def init_model(self, key: jax.Array, spec: Spec) -> Any:
        kq, kp = jax.random.split(key)
        ex = spec.example()
        x, xa = observe(self.problem, ex.s, ex.g), observe_action(self.problem, ex.s, ex.g, ex.a)
        critic = init_ensemble(self.critic_net, kq, xa)
        actor = mlp(self.config, spec.action_dim).init(kp, x)
        return {"critic": critic, "actor": actor, "target_critic": critic,
                "target_actor": actor, "critic_opt": self.optimizer.init(critic),
                "actor_opt": self.optimizer.init(actor)}

    def pi(self, actor: Any, s: jax.Array, g: jax.Array | None) -> jax.Array:
        return squash(self.problem, apply_mlp(self.config, actor, observe(self.problem, s, g)))

    def q_values(self, critic: Any, s, g, a) -> jax.Array:
        x = observe_action(self.problem, s, g, a)
        return apply_ensemble(self.critic_net, critic, x)[..., 0]

    def critic_loss(self, critic, model, b: Transitions, key):
        cfg, c = self.config, self.problem.action_length
        a_next = self.pi(model["target_actor"], b.s_next, b.g)
        noise = jnp.clip(cfg.policy_noise * c * jax.random.normal(key, a_next.shape),
                         -cfg.noise_clip * c, cfg.noise_clip * c)
        a_next = project(self.problem, a_next + noise)
        q_next = jnp.min(self.q_values(model["target_critic"], b.s_next, b.g, a_next), axis=0)
        y = jax.lax.stop_gradient(b.r + cfg.gamma * mask_of(b) * q_next)
        q = self.q_values(critic, b.s, b.g, b.a)
        return jnp.sum(jnp.mean((q - y) ** 2, axis=1)), jnp.mean(q)

    def actor_loss(self, actor, critic, b: Transitions):
        action = self.pi(actor, b.s, b.g)
        first = jax.tree.map(lambda p: p[:1], critic)  # Q1 as a one-member ensemble
        q1 = self.q_values(first, b.s, b.g, action)[0]
        lam = self.config.alpha / jnp.maximum(jax.lax.stop_gradient(jnp.mean(jnp.abs(q1))), 1e-6)
        bc = jnp.mean(jnp.sum((action - b.a) ** 2, axis=-1)) / self.problem.action_length ** 2
        return -lam * jnp.mean(q1) + bc, bc

    def update(self, model, b, key, step):
        cfg = self.config
        (q_loss, q_mean), grads = jax.value_and_grad(self.critic_loss, has_aux=True)(
            model["critic"], model, b, key)
        updates, critic_opt = self.optimizer.update(grads, model["critic_opt"], model["critic"])
        critic = optax.apply_updates(model["critic"], updates)

        (p_loss, bc), grads = jax.value_and_grad(self.actor_loss, has_aux=True)(
            model["actor"], critic, b)
        updates, actor_opt = self.optimizer.update(grads, model["actor_opt"], model["actor"])
        actor = optax.apply_updates(model["actor"], updates)
        # Delayed policy updates: computed every step (vmap turns a cond into a select
        # anyway), kept every policy_freq-th step.
        delayed = (step % cfg.policy_freq) == 0
        actor, actor_opt = select(delayed, (actor, actor_opt), (model["actor"], model["actor_opt"]))
        targets = select(delayed, (polyak(model["target_critic"], critic, cfg.tau),
                                   polyak(model["target_actor"], actor, cfg.tau)),
                         (model["target_critic"], model["target_actor"]))
        model = {"critic": critic, "actor": actor, "target_critic": targets[0],
                 "target_actor": targets[1], "critic_opt": critic_opt, "actor_opt": actor_opt}
        return model, {"critic_loss": q_loss, "actor_loss": p_loss, "bc_loss": bc,
                       "q_mean": q_mean}

    def actions(self, model, s, g):
        return self.pi(model["actor"], s, g)


def make(config: TD3BCConfig | None = None, problem: Problem | None = None,
         progress=None) -> TD3BC:
    """The TD3+BC agent (``config`` None: the defaults)."""
    return TD3BC(config, problem, progress)
