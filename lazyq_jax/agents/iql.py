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
  ``L_pi = -E[min(exp(beta A), max_weight) log pi(a | s, g)]``, ``A = Q_t - V``,
  ``beta = temperature`` (3), with the advantages in units of their minibatch standard
  deviation (``normalize_advantages``, see below).

Target critics follow the critics by Polyak averaging (``tau`` 0.005).

The actor has fixed concentration (:func:`~lazyq_jax.agents.common.log_likelihood`):
on the sphere (``"ball"``) a von Mises-Fisher distribution with mean direction
``mu = u / |u|`` (``u`` the network's ``n_a`` outputs), ``log pi(a) = kappa cos(a, mu) +
const``; in the box a Gaussian with mean ``c tanh(u)``.  For any fixed concentration the
weighted likelihood has the same maximiser (the concentration only scales the loss,
which Adam undoes), and acting uses the mode ``c mu``.

Normalised advantages.  With 0/1 rewards and ``gamma = 0.9`` one move is worth ~0.05-0.1
of value, so raw advantages have a minibatch std of ~0.07 and ``exp(3 A)`` weighs the
data almost uniformly (0.7-2.7).  Measured on the 2-D line task
(``experiments/agents_synthetic.py``, 20,000 rows, default budget, scored after each
block; fraction of probe actions within 26 degrees of the optimum): the critics are
good (the AWR direction they imply, the ``exp(3 A)``-weighted mean over 360 directions,
is within 26 degrees for 97-99 % of probes from step 4840 on), but the actor, fitting
one random direction per row with so flat weights, learns the behaviour's noise: 0.59
at step 4840, 0.32 at the end (median cos 0.76).  A Gaussian actor (fixed std, OGBench's
``const_std``) is worse (0.26), a cosine-decayed actor learning rate (the authors'
code) does not help; sharper weights do: raw ``beta = 10``: 0.72 (mean of the last
five blocks 0.78); advantages divided by their minibatch std with ``beta`` 0.5, 1, 3:
0.59, 0.73 (0.79), 0.78 (0.79).  The budget matters as much: on 1,000,000 rows (the
default budget's ~10 epochs; 20,000 rows make it ~5,000) the unchanged IQL reaches
1.00 (median cos 0.997), and so does this one (1.00, 0.998).  So the advantages are
normalised (the temperature is then free of the reward scale and discount) and
``beta`` stays 3: on the 20,000 rows 0.76 (median cos 0.97) instead of 0.32.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import jax
import jax.numpy as jnp
import optax

from lazyq_jax.agents.base import Problem, Spec
from lazyq_jax.agents.common import (Baseline, BaselineConfig, apply_ensemble, apply_mlp, check,
                                     check_range, init_ensemble, log_likelihood, mask_of, mlp,
                                     observe, observe_action, polyak, squash)
from lazyq_jax.types import Transitions


@dataclasses.dataclass(frozen=True)
class IQLConfig(BaselineConfig):
    """:class:`BaselineConfig` plus ``tau`` (Polyak rate of the target critics),
    ``expectile`` (of the value regression), ``temperature`` (AWR ``beta``),
    ``max_weight`` (cap of the AWR weights) and ``normalize_advantages`` (divide the
    advantages by their minibatch standard deviation before the temperature; False:
    raw advantages, as the published IQL and this agent before, see the module
    docstring)."""

    tau: float = 0.005
    expectile: float = 0.9
    temperature: float = 3.0
    max_weight: float = 100.0
    normalize_advantages: bool = True

    def __post_init__(self) -> None:
        super().__post_init__()
        check_range(self, "tau", 0.0, 1.0, lo_open=True)
        check_range(self, "expectile", 0.0, 1.0, lo_open=True, hi_open=True)
        check_range(self, "temperature", 0.0, math.inf)
        check_range(self, "max_weight", 0.0, math.inf, lo_open=True)
        check(isinstance(self.normalize_advantages, bool),
              f"IQLConfig.normalize_advantages must be True or False, got "
              f"{self.normalize_advantages!r}")


class IQL(Baseline):
    name = "iql"
    config_class = IQLConfig

    def __init__(self, config=None, problem=None, progress=None):
        super().__init__(config, problem, progress)
        self.value_net, self.critic_net = mlp(self.config, 1), mlp(self.config, 1)
        self.optimizer = optax.adam(self.config.learning_rate)

    def init_model(self, key: jax.Array, spec: Spec) -> Any:
        kv, kq, kp = jax.random.split(key, 3)
        ex = spec.example()
        x, xa = observe(self.problem, ex.s, ex.g), observe_action(self.problem, ex.s, ex.g, ex.a)
        params = {"value": self.value_net.init(kv, x),
                  "critic": init_ensemble(self.critic_net, kq, xa),
                  "actor": mlp(self.config, spec.action_dim).init(kp, x)}
        return {"params": params, "target_critic": params["critic"],
                "opt": self.optimizer.init(params)}

    def pi(self, actor: Any, s: jax.Array, g: jax.Array | None) -> jax.Array:
        return squash(self.problem, apply_mlp(self.config, actor, observe(self.problem, s, g)))

    def loss(self, params: Any, target_critic: Any, b: Transitions):
        cfg, problem = self.config, self.problem
        x = observe(problem, b.s, b.g)
        xa = observe_action(problem, b.s, b.g, b.a)
        q_t = jnp.min(apply_ensemble(self.critic_net, target_critic, xa)[..., 0], axis=0)
        v = self.value_net.apply(params["value"], x)[:, 0]
        d = q_t - v
        value_loss = jnp.mean(jnp.where(d < 0, 1.0 - cfg.expectile, cfg.expectile) * d ** 2)

        v_next = jax.lax.stop_gradient(
            self.value_net.apply(params["value"], observe(problem, b.s_next, b.g))[:, 0])
        y = b.r + cfg.gamma * mask_of(b) * v_next
        q = apply_ensemble(self.critic_net, params["critic"], xa)[..., 0]  # [2, B]
        critic_loss = jnp.sum(jnp.mean((q - y) ** 2, axis=1))

        adv = q_t - jax.lax.stop_gradient(v)
        if cfg.normalize_advantages:  # in units of their minibatch standard deviation
            adv = adv / (jnp.std(adv) + 1e-6)
        weight = jnp.minimum(jnp.exp(cfg.temperature * adv), cfg.max_weight)
        log_prob = log_likelihood(problem, self.pi(params["actor"], b.s, b.g), b.a)
        actor_loss = -jnp.mean(weight * log_prob)
        metrics = {"value_loss": value_loss, "critic_loss": critic_loss,
                   "actor_loss": actor_loss, "q_mean": jnp.mean(q_t),
                   "adv_std": jnp.std(q_t - v), "weight_mean": jnp.mean(weight),
                   "weight_max": jnp.max(weight)}
        return value_loss + critic_loss + actor_loss, metrics

    def update(self, model, batch, key, step):
        grads, metrics = jax.grad(self.loss, has_aux=True)(model["params"],
                                                           model["target_critic"], batch)
        updates, opt = self.optimizer.update(grads, model["opt"], model["params"])
        params = optax.apply_updates(model["params"], updates)
        target = polyak(model["target_critic"], params["critic"], self.config.tau)
        return {"params": params, "target_critic": target, "opt": opt}, metrics

    def actions(self, model, s, g):
        return self.pi(model["params"]["actor"], s, g)


def make(config: IQLConfig | None = None, problem: Problem | None = None,
         progress=None) -> IQL:
    """The IQL agent (``config`` None: the defaults)."""
    return IQL(config, problem, progress)
