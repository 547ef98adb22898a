"""Pieces every neighbour search shares: the result type, the float32 membership
thresholds (radius tables, the wrapped angle) and the bit tricks of the samplers."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

PI = np.float32(np.pi)
TWO_PI = np.float32(2 * np.pi)


@struct.dataclass
class Neighbours:
    """Result of a neighbour search for ``Q`` queries.

    * ``idx``: int32 ``[Q, k]``: distinct indices into the data, uniform without
      replacement from ``B_level`` (a uniform k-subset; the column order is not a
      uniform random order, so take all k columns, not a prefix).
    * ``level``: int32 ``[Q]``: growths applied (radii ``radius * growth**level``).
    * ``count``: int32 ``[Q]``: ``|B_level|``.

    ``level == -1`` (and ``idx == -1``) only from :func:`query_neighbours` for a
    query that needs more than ``index.max_level`` growths.
    """

    idx: jax.Array
    level: jax.Array
    count: jax.Array

    @property
    def found(self) -> jax.Array:
        return self.level >= 0



def _check_params(k, radius_s, radius_g, growth):
    if not isinstance(k, (int, np.integer)) or isinstance(k, bool) or k <= 0:
        raise ValueError(f"k must be a positive int, got {k!r}")
    for name, v in (("radius_s", radius_s), ("radius_g", radius_g), ("growth", growth)):
        if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
            raise ValueError(f"{name} must be a real number, got {v!r}")  # noqa: TRY004 (one error type)
    for name, v in (("radius_s", radius_s), ("radius_g", radius_g)):
        if not np.isfinite(v) or v <= 0:
            raise ValueError(f"{name} must be a finite positive number, got {v!r}")
    if not np.isfinite(growth) or growth <= 1:
        raise ValueError(f"growth must be a finite number > 1 (radii grow each level), got {growth!r}")



def wrap_angle(g):
    """``g - 2pi*floor((g + pi)/2pi)`` in float32 (NumPy or JAX arrays): the goal in ``[-pi, pi]``."""
    xp = jnp if isinstance(g, jax.Array) else np
    g = xp.asarray(g, dtype=xp.float32)
    return g - TWO_PI * xp.floor((g + PI) / TWO_PI)


def radius_tables(radius_s, radius_g, growth, levels):
    """float32 ``(R2S, RG)`` for the given levels: the thresholds of the membership test."""
    lv = np.asarray(levels, np.float64)
    r2s = ((radius_s * growth**lv) ** 2).astype(np.float32)
    rg = (radius_g * growth**lv).astype(np.float32)
    return r2s, rg



def _pick_level(words, item_q, n_queries: int, k: int, lo: int):
    """Each query's level: the smallest of ``lo, lo + 1, ...`` whose ball holds ``k``
    members, from the items' membership words ``[T, levels]`` (items sorted by query).

    Returns ``(found, li, level, m)``: ``found`` if any level has ``k``; ``li`` its
    column of ``words``; ``level`` (``-1`` where none) and ``m = |B_level|`` (where none,
    the members at the last level).
    """
    counts = jax.ops.segment_sum(jax.lax.population_count(words).astype(jnp.int32), item_q,
                                 num_segments=n_queries, indices_are_sorted=True)  # [Q, levels]
    enough = counts >= k
    found = enough.any(axis=1)
    li = jnp.argmax(enough, axis=1)
    level = jnp.where(found, lo + li, -1)
    m = jnp.where(found, jnp.take_along_axis(counts, li[:, None], 1)[:, 0], counts[:, -1])
    return found, li, level, m


def _mix32(x):
    """lowbias32 integer hash (uint32 -> uint32)."""
    x = x ^ (x >> 16)
    x = x * jnp.uint32(0x7FEB352D)
    x = x ^ (x >> 15)
    x = x * jnp.uint32(0x846CA68B)
    return x ^ (x >> 16)



def _select_bit(word, r):
    """Position of the ``r``-th (0-based) set bit of ``word``."""
    pos = jnp.zeros_like(r)
    for step in (16, 8, 4, 2, 1):
        mid = pos + step
        below = jax.lax.population_count(word & ((jnp.uint32(1) << mid.astype(jnp.uint32)) - 1))
        pos = jnp.where(below.astype(jnp.int32) <= r, mid, pos)
    return pos

