"""Filtered behaviour cloning: imitate only the transitions that earned a positive reward.

"%BC" / filtered BC as in Chen et al., "Decision Transformer", NeurIPS 2021 (§5) and
Emmons et al., "RvS: What is Essential for Offline RL via Supervised Learning?",
ICLR 2022: behaviour cloning on the best part of the data, here the rows with
``r > 0`` (for the push task a correct push, Eq. 15).

Deterministic actor in the action set (``c u / |u|`` or ``c tanh(u)``), trained by
maximum likelihood of the fixed-concentration policy around it
(:func:`~lazyq_jax.agents.common.log_likelihood`: ``-E[cos(pi, a)]`` on the sphere, as
the IQL actor with unit weights; ``E[|pi - a|^2] / (2 c^2)`` in the box) over positive
rows, each minibatch drawn uniformly with replacement among the positive rows
``< n_valid``.  A dataset without a positive row leaves the actor at its
initialisation (no update is applied) and reports ``positives = 0``.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import optax

from lazyq_jax.agents.base import Problem, Spec
from lazyq_jax.agents.common import (Baseline, BaselineConfig, Sampler, apply_mlp, log_likelihood,
                                     mlp, observe, squash)
from lazyq_jax.types import Transitions


@dataclasses.dataclass(frozen=True)
class BCConfig(BaselineConfig):
    """:class:`BaselineConfig` (``gamma`` is unused)."""


class BC(Baseline):
    name = "bc"
    config_class = BCConfig

    def __init__(self, config=None, problem=None, progress=None):
        super().__init__(config, problem, progress)
        self.optimizer = optax.adam(self.config.learning_rate)

    def init_model(self, key: jax.Array, spec: Spec) -> Any:
        ex = spec.example()
        params = mlp(self.config, spec.action_dim).init(key, observe(self.problem, ex.s, ex.g))
        return {"params": params, "opt": self.optimizer.init(params)}

    def pi(self, params, s, g):
        return squash(self.problem, apply_mlp(self.config, params, observe(self.problem, s, g)))

    def sampler(self, data: Transitions, n_valid: jax.Array) -> Sampler:
        n = data.r.shape[0]
        positive = (jnp.arange(n) < n_valid) & (data.r > 0)
        count = jnp.sum(positive, dtype=jnp.int32)
        rows = jnp.nonzero(positive, size=n, fill_value=0)[0]

        def draw(key):
            return rows[jax.random.randint(key, (self.config.batch_size,), 0,
                                           jnp.maximum(count, 1))]

        return draw, count > 0, {"positives": count}

    def loss(self, params, b: Transitions):
        log_prob = log_likelihood(self.problem, self.pi(params, b.s, b.g), b.a)
        return -jnp.mean(log_prob), jnp.mean(log_prob)

    def update(self, model, b, key, step):
        (loss, log_prob), grads = jax.value_and_grad(self.loss, has_aux=True)(model["params"], b)
        updates, opt = self.optimizer.update(grads, model["opt"], model["params"])
        return ({"params": optax.apply_updates(model["params"], updates), "opt": opt},
                {"loss": loss, "log_prob": log_prob})

    def actions(self, model, s, g):
        return self.pi(model["params"], s, g)


def make(config: BCConfig | None = None, problem: Problem | None = None,
         progress=None) -> BC:
    """The filtered BC agent (``config`` None: the defaults)."""
    return BC(config, problem, progress)
