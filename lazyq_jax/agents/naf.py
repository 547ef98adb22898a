"""Normalized Advantage Functions, with the maximiser in the action set.

Gu, Lillicrap, Sutskever & Levine, "Continuous Deep Q-Learning with Model-based
Acceleration", ICML 2016 (arXiv:1603.00748; the lazy-Q paper's ref. [11]), Eq. 3:

    Q(s, a, g) = V(s, g) - 1/2 (a' - mu)^T P (a' - mu),   P = L L^T,

with ``a' = a / c`` (action units, for conditioning), ``L`` an ``n_a x n_a`` lower
triangular matrix with exponentiated diagonal (log-diagonal clipped to [-8, 8]
against overflow; ``P`` is positive definite) and ``mu`` IN the action set:
``mu = u / |u|`` on the unit sphere (``"ball"``: the actions are the sphere
``|a| = c``) or ``mu = tanh(u)`` inside the box (``"box"``).  With ``mu`` feasible,
``max_a Q = Q(mu) = V`` exactly, so the target ``y = r + gamma (1 - done) V_t(s', g)``
bootstraps from a feasible action.  (Textbook NAF, with ``mu`` unconstrained,
bootstraps from ``V = Q(mu)`` at a point inside the circle that no action reaches; in
a trial its values inflated away from terminal states and the policy pointed
backwards.)

Loss ``E[(Q(s, a, g) - y)^2]``; the target network follows by Polyak averaging
(``tau`` 0.005); the policy is ``c mu``.  The network's ``1 + n_a + n_a (n_a + 1) / 2``
outputs are ``V``, ``u`` and the lower triangle of ``L`` (row by row).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax

from lazyq_jax.agents.base import Problem, Spec
from lazyq_jax.agents.common import (Baseline, BaselineConfig, apply_mlp, check_range, mask_of, mlp,
                                     observe, polyak, squash)
from lazyq_jax.types import Transitions

LOG_DIAG_CLIP = 8.0


@dataclasses.dataclass(frozen=True)
class NAFConfig(BaselineConfig):
    """:class:`BaselineConfig` plus ``tau`` (Polyak rate of the target network)."""

    tau: float = 0.005

    def __post_init__(self) -> None:
        super().__post_init__()
        check_range(self, "tau", 0.0, 1.0, lo_open=True)


def action_dim_of(outputs: int) -> int:
    """``n_a`` from the head width ``1 + n_a + n_a (n_a + 1) / 2``."""
    n = round((-3 + math.sqrt(9 + 8 * (outputs - 1))) / 2)
    assert 1 + n + n * (n + 1) // 2 == outputs, outputs
    return n


def lower_triangular(flat: jax.Array, n: int) -> jax.Array:
    """``[..., n (n + 1) / 2] -> [..., n, n]``: ``L`` with exponentiated (clipped) diagonal."""
    rows, cols = np.tril_indices(n)
    entries = jnp.where(rows == cols, jnp.exp(jnp.clip(flat, -LOG_DIAG_CLIP, LOG_DIAG_CLIP)),
                        flat)
    return jnp.zeros((*flat.shape[:-1], n, n), flat.dtype).at[..., rows, cols].set(entries)


class NAF(Baseline):
    name = "naf"
    config_class = NAFConfig

    def __init__(self, config=None, problem=None, progress=None):
        super().__init__(config, problem, progress)
        self.optimizer = optax.adam(self.config.learning_rate)

    def init_model(self, key: jax.Array, spec: Spec) -> Any:
        n = spec.action_dim
        ex = spec.example()
        params = mlp(self.config, 1 + n + n * (n + 1) // 2).init(
            key, observe(self.problem, ex.s, ex.g))
        return {"params": params, "target": params, "opt": self.optimizer.init(params)}

    def heads(self, params, s, g):
        """``(V [B], mu [B, n_a] in action units, L [B, n_a, n_a])``."""
        out = apply_mlp(self.config, params, observe(self.problem, s, g))
        n = action_dim_of(out.shape[-1])
        mu = squash(self.problem, out[:, 1:1 + n]) / self.problem.action_length
        return out[:, 0], mu, lower_triangular(out[:, 1 + n:], n)

    def q_value(self, params, s, g, a):
        """``(Q, V, advantage)``, each ``[B]``."""
        v, mu, l = self.heads(params, s, g)
        d = jnp.asarray(a, jnp.float32) / self.problem.action_length - mu
        lt_d = jnp.einsum("bji,bj->bi", l, d)  # L^T (a' - mu)
        advantage = -0.5 * jnp.sum(lt_d ** 2, axis=-1)
        return v + advantage, v, advantage

    def loss(self, params, target, b: Transitions):
        v_next = self.heads(target, b.s_next, b.g)[0]
        y = jax.lax.stop_gradient(b.r + self.config.gamma * mask_of(b) * v_next)
        q, v, adv = self.q_value(params, b.s, b.g, b.a)
        loss = jnp.mean((q - y) ** 2)
        return loss, {"loss": loss, "v_mean": jnp.mean(v), "advantage_mean": jnp.mean(adv)}

    def update(self, model, b, key, step):
        grads, metrics = jax.grad(self.loss, has_aux=True)(model["params"], model["target"], b)
        updates, opt = self.optimizer.update(grads, model["opt"], model["params"])
        params = optax.apply_updates(model["params"], updates)
        return {"params": params, "target": polyak(model["target"], params, self.config.tau),
                "opt": opt}, metrics

    def actions(self, model, s, g):
        return self.problem.action_length * self.heads(model["params"], s, g)[1]


def make(config: NAFConfig | None = None, problem: Problem | None = None,
         progress=None) -> NAF:
    """The NAF agent (``config`` None: the defaults)."""
    return NAF(config, problem, progress)
