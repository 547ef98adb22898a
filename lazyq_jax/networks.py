"""The value network V(s, g) of §V-A-4: Dense and BatchNorm layers in alternating order."""

from __future__ import annotations

import math

import flax.linen as nn
import jax
import jax.numpy as jnp

#: The largest distance the ``"distance"`` head is regressed towards, in horizons
#: ``1 / (1 - gamma)`` (:func:`value_to_distance`): ``gamma^d`` is then ``~6e-6``, near float32's
#: resolution of ``1 + (1 - gamma) V``; values at or below it are capped there.
DISTANCE_CAP = 12.0


def distance_to_value(u: jax.Array, gamma: float) -> jax.Array:
    """``V = -(1 - gamma^d) / (1 - gamma)`` of ``d = u / (1 - gamma)`` steps (``u``: the
    distance in horizons, at least 0): the discounted return of a reward of -1 every step for
    ``d`` steps, then 0 (OGBench's goal reaching, reward ``success - 1``)."""
    d = jnp.maximum(u, 0.0) / (1.0 - gamma)
    return jnp.expm1(d * math.log(gamma)) / (1.0 - gamma)


def value_to_distance(v: jax.Array, gamma: float) -> tuple[jax.Array, jax.Array]:
    """The inverse of :func:`distance_to_value`: ``(u, capped)`` with ``u = (1 - gamma)
    log(1 + (1 - gamma) V) / log(gamma)`` in horizons, capped at :data:`DISTANCE_CAP` (where
    ``V <= -1 / (1 - gamma)`` or so close to it that the logarithm has no precision left:
    ``capped`` marks those); a value above 0 gives a distance below 0."""
    x = (1.0 - gamma) * jnp.asarray(v, jnp.float32)
    floor = math.expm1(DISTANCE_CAP * math.log(gamma) / (1.0 - gamma))  # > -1
    capped = x <= floor
    u = (1.0 - gamma) * jnp.log1p(jnp.maximum(x, floor)) / math.log(gamma)
    return jnp.where(capped, DISTANCE_CAP, u), capped


def goal_kind(g) -> str | int | None:
    """``"angle"`` for goals ``[N]`` (an angle), ``d_g`` for ``[N, d_g]`` (a vector), ``None``
    for no goal: the shapes decide (the ``goal`` argument of :func:`make_train`)."""
    if g is None:
        return None
    ndim = len(g.shape) if hasattr(g, "shape") else len(g)
    if ndim == 1:
        return "angle"
    if ndim == 2:
        return int(g.shape[1])
    raise ValueError(f"goals must be [N] (an angle) or [N, d_g] (a vector), got shape {g.shape}")


def encode(s: jax.Array, g: jax.Array | None, state_scale=1.0) -> jax.Array:
    """Network input: the state divided by ``state_scale`` (a number or one per dimension),
    then the goal: an angle ``g[...]`` as ``(cos g, sin g)`` (continuous across +-pi), a
    vector ``g[..., d_g]`` as it is, or nothing for ``g = None``.  For the push task:
    ``(x / scale, y / scale, cos g, sin g)``."""
    parts = [jnp.asarray(s, jnp.float32) / jnp.asarray(state_scale, jnp.float32)]
    if g is not None:
        g = jnp.asarray(g, jnp.float32)
        if g.ndim == parts[0].ndim - 1:  # an angle per row
            parts += [jnp.cos(g)[..., None], jnp.sin(g)[..., None]]
        else:
            parts.append(g)
    return jnp.concatenate(parts, axis=-1)


class ValueNetwork(nn.Module):
    """``depth`` Dense layers of ``width`` units with BatchNorm + ReLU between them.

    With the paper's ``depth = 9``: Dense, BN, ReLU, ..., Dense(1); the last
    Dense is linear and outputs the value.  Call as ``apply(variables, s, g, train=...)``
    with ``s: [B, d_s]`` and ``g: [B]`` (an angle), ``[B, d_g]`` (a vector) or ``None``
    (see :func:`encode`); returns ``V: [B]``.

    The hidden Dense layers have no bias: batch norm subtracts the batch mean, so
    such a bias would get an exactly zero gradient and only drift with rounding
    noise (which Adam scales up to ``learning_rate``-sized steps).

    ``output_init``: the last Dense layer's initial bias, so ``V`` (or the distance, with
    ``distance_gamma``) starts near it (a pessimistic start: ``TrainConfig.value_init``).

    ``distance_gamma``: the last layer outputs a distance ``u`` to the goal in horizons
    ``1 / (1 - gamma)`` (``TrainConfig.value_head="distance"``) and the network returns
    ``V = distance_to_value(u, gamma)``, or ``u`` itself with ``distance=True`` (the head
    the regression fits).  ``None``: the last layer outputs ``V``.

    ``norm="layer"`` (``TrainConfig.norm``, an ablation) builds OGBench's MLP block instead
    (Park et al. 2024, ``impls/utils/networks.py``): Dense with bias, GELU, LayerNorm; no
    batch statistics, so training and inference compute the same function.

    ``axis_name``: inside ``shard_map`` over a batch split on that mesh axis, batch
    norm averages its statistics over all devices (synchronised batch norm: the
    same statistics as the whole batch on one device).  The parameters do not
    depend on it.
    """

    width: int = 64
    depth: int = 9
    state_scale: float | tuple[float, ...] = 1.0
    axis_name: str | None = None
    output_init: float = 0.0
    norm: str = "batch"
    distance_gamma: float | None = None

    @nn.compact
    def __call__(self, s: jax.Array, g: jax.Array | None = None, train: bool = False,
                 distance: bool = False) -> jax.Array:
        x = encode(s, g, self.state_scale)
        for _ in range(self.depth - 1):
            if self.norm == "layer":  # OGBench's block
                x = nn.LayerNorm()(nn.gelu(nn.Dense(self.width)(x)))
                continue
            x = nn.Dense(self.width, use_bias=False)(x)  # BN's bias replaces it
            x = nn.BatchNorm(use_running_average=not train, momentum=0.99,
                             axis_name=self.axis_name if train else None)(x)
            x = nn.relu(x)
        head = nn.Dense(1, bias_init=nn.initializers.constant(self.output_init))(x)[..., 0]
        if self.distance_gamma is None:
            if distance:
                raise ValueError("distance=True needs a distance head (ValueNetwork(distance_gamma=...))")
            return head
        return head if distance else distance_to_value(head, self.distance_gamma)
