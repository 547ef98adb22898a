"""Exact rejection samplers for finger starts (uniform on the allowed region)."""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp


def rejection_sample(key: jax.Array, propose: Callable[[jax.Array], jax.Array],
                     accept: Callable[[jax.Array], jax.Array]) -> jax.Array:
    """Draw ``propose(key)`` until ``accept(x)``; one sample, vmappable, jittable.

    The result is distributed as the proposal conditioned on acceptance.  Callers
    make sure the acceptance probability is not tiny (the loop has no cap).
    """

    def cond(carry):
        return ~carry[2]

    def body(carry):
        key, _, _ = carry
        key, sub = jax.random.split(key)
        x = propose(sub)
        return key, x, accept(x)

    key, sub = jax.random.split(key)
    x0 = propose(sub)
    _, x, _ = jax.lax.while_loop(cond, body, (key, x0, accept(x0)))
    return x


def sample_outside_disk(key: jax.Array, center: jax.Array, half_width: float,
                        min_dist: float, extra: Callable[[jax.Array], jax.Array] | None = None
                        ) -> jax.Array:
    """A point uniform in the square ``center + [-half_width, half_width]^2`` with
    ``|x - center_disk| > min_dist`` (``center`` is the disk centre) and ``extra(x)`` true.
    """
    center = jnp.asarray(center, jnp.float32)

    def propose(k):
        return center + jax.random.uniform(k, (2,), jnp.float32, -half_width, half_width)

    def accept(x):
        ok = jnp.linalg.norm(x - center) > min_dist
        return ok if extra is None else ok & extra(x)

    return rejection_sample(key, propose, accept)
