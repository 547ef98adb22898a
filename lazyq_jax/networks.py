"""The value network V(s, g) of §V-A-4: Dense and BatchNorm layers in alternating order."""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp


def encode(s: jax.Array, g: jax.Array, state_scale: float = 1.0) -> jax.Array:
    """Network input ``(x / scale, y / scale, cos g, sin g)``: continuous across g = +-pi."""
    g = jnp.asarray(g, jnp.float32)
    return jnp.concatenate([jnp.asarray(s, jnp.float32) / state_scale,
                            jnp.cos(g)[..., None], jnp.sin(g)[..., None]], axis=-1)


class ValueNetwork(nn.Module):
    """``depth`` Dense layers of ``width`` units with BatchNorm + ReLU between them.

    With the paper's ``depth = 9``: Dense, BN, ReLU, ..., Dense(1); the last
    Dense is linear and outputs the value.  Call as ``apply(variables, s, g, train=...)``
    with ``s: [B, 2]``, ``g: [B]``; returns ``V: [B]``.

    The hidden Dense layers have no bias: batch norm subtracts the batch mean, so
    such a bias would get an exactly zero gradient and only drift with rounding
    noise (which Adam scales up to ``learning_rate``-sized steps).

    ``axis_name``: inside ``shard_map`` over a batch split on that mesh axis, batch
    norm averages its statistics over all devices (synchronised batch norm: the
    same statistics as the whole batch on one device).  The parameters do not
    depend on it.
    """

    width: int = 64
    depth: int = 9
    state_scale: float = 1.0
    axis_name: str | None = None

    @nn.compact
    def __call__(self, s: jax.Array, g: jax.Array, train: bool = False) -> jax.Array:
        x = encode(s, g, self.state_scale)
        for _ in range(self.depth - 1):
            x = nn.Dense(self.width, use_bias=False)(x)  # BN's bias replaces it
            x = nn.BatchNorm(use_running_average=not train, momentum=0.99,
                             axis_name=self.axis_name if train else None)(x)
            x = nn.relu(x)
        return nn.Dense(1)(x)[..., 0]
