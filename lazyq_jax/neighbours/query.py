"""Jittable neighbourhood queries in general spaces, for small batches (a policy step).

:func:`lazyq_jax.neighbours.nd.find_neighbours_nd` answers all of a dataset's queries
at once (host-driven passes, grids, growth without limit).  A policy acting in a
``lax.scan`` rollout needs the same neighbourhoods ``B(s0, g0)`` (§V-A-2) for a few
queries at a time, inside ``jit``.  This module answers them by scanning the whole
dataset: for every data point its *entry level* (the smallest ``L`` with the point in
``B_L``, by the exact float32 formula of :mod:`lazyq_jax.neighbours.nd`, through
``searchsorted`` on the radius tables), the query's level as the smallest ``L`` with
at least ``k`` points at or below it, and ``k`` members drawn uniformly without
replacement (the ``k`` largest of independent uniform keys among the members).

Cost ``O(N (d_s + d_g))`` per query, no index and no layout to choose, any ``d_s``,
``d_g`` and goal kind; queries run ``batch`` at a time through ``lax.map`` (memory
``O(batch N)``); about 14 ms a query at N = 1M on a 2-core CPU.  The 2-D state +
angle case keeps its grid
(:func:`lazyq_jax.neighbours.grid.query_neighbours`), which is far cheaper per query.
A query needing more than ``max_level`` growths gets ``level == -1`` and
``idx == -1`` (as :func:`lazyq_jax.neighbours.grid.query_neighbours`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from lazyq_jax.neighbours.common import TWO_PI, Neighbours, _check_params, radius_tables, wrap_angle
from lazyq_jax.neighbours.nd import _points

__all__ = ["ScanIndex", "build_scan_index", "query_neighbours_scan"]


@struct.dataclass
class ScanIndex:
    """A dataset's columns for :func:`query_neighbours_scan` (a pytree: pass it into ``jit``)."""

    cols: jax.Array  # float32 [d_s + d_g, N]: states, then the wrapped angle or the goal vector
    k: int = struct.field(pytree_node=False)
    radius_s: float = struct.field(pytree_node=False)
    radius_g: float = struct.field(pytree_node=False)
    growth: float = struct.field(pytree_node=False)
    d_s: int = struct.field(pytree_node=False)
    goal: str = struct.field(pytree_node=False)  # "angle" | "vector" | "none"
    max_level: int = struct.field(pytree_node=False)


def build_scan_index(data_s, data_g=None, *, k=20, radius_s=0.06, radius_g=0.1, growth=2 ** (1 / 3),
                     max_level=8) -> ScanIndex:
    """Validate the data (shapes, NaN/inf, ``k <= N``) and keep its columns for queries."""
    _check_params(k, radius_s, radius_g, growth)
    if not isinstance(max_level, (int, np.integer)) or max_level < 0:
        raise ValueError(f"max_level must be an int >= 0, got {max_level!r}")
    cols, d_s, kind, _ = _points(data_s, data_g, "data")
    if cols.shape[1] < k:
        raise ValueError(f"need at least k={k} data points to draw k distinct neighbours, got {cols.shape[1]}")
    return ScanIndex(jnp.asarray(cols), int(k), float(radius_s), float(radius_g), float(growth), d_s, kind,
                     int(max_level))


def _sq(v):
    """``v*v`` rounded to float32 before any add (no fused multiply-add; see neighbours_nd)."""
    return jnp.maximum(v * v, jnp.float32(0))


def entry_levels(index: ScanIndex, q):
    """``[N]`` int32: each data point's smallest level ``L <= max_level`` with the point in
    ``B_L(q)`` (``max_level + 1`` if none); ``q [d_s + d_g]`` one query's columns."""
    levels = np.arange(index.max_level + 1)
    r2s, rg = radius_tables(index.radius_s, index.radius_g, index.growth, levels)
    rg2, _ = radius_tables(index.radius_g, index.radius_g, index.growth, levels)
    c, d_s = index.cols, index.d_s
    ds2 = _sq(c[0] - q[0])
    for i in range(1, d_s):
        ds2 = ds2 + _sq(c[i] - q[i])
    # compare_all: a few table entries against every point, fused (the default binary
    # search is a while loop per point, ~25x slower on a CPU at N = 1M).
    lam = jnp.searchsorted(jnp.asarray(r2s), ds2, side="right", method="compare_all")
    if index.goal == "angle":
        d = jnp.abs(c[d_s] - q[d_s])
        lam = jnp.maximum(lam, jnp.searchsorted(jnp.asarray(rg), jnp.minimum(d, TWO_PI - d), side="right",
                                                    method="compare_all"))
    elif index.goal == "vector":
        dg2 = _sq(c[d_s] - q[d_s])
        for i in range(d_s + 1, c.shape[0]):
            dg2 = dg2 + _sq(c[i] - q[i])
        lam = jnp.maximum(lam, jnp.searchsorted(jnp.asarray(rg2), dg2, side="right",
                                                    method="compare_all"))
    return lam.astype(jnp.int32)


def _one(index: ScanIndex, key, q):
    lam = entry_levels(index, q)
    # |B_L| for every L: a histogram of the entry levels, summed up (O(N), not O(levels N)).
    counts = jnp.cumsum(jnp.bincount(lam, length=index.max_level + 2))[:-1]
    enough = counts >= index.k
    found = enough.any()
    level = jnp.where(found, jnp.argmax(enough), -1).astype(jnp.int32)
    u = jax.random.uniform(key, lam.shape, minval=0.5, maxval=1.0)  # members: keys > 0
    _, idx = jax.lax.top_k(jnp.where((lam <= level) & found, u, 0.0), index.k)
    count = jnp.where(found, counts[jnp.maximum(level, 0)], 0)
    return jnp.where(found, idx.astype(jnp.int32), -1), level, count.astype(jnp.int32)


def query_neighbours_scan(index: ScanIndex, key, query_s, query_g=None, *,
                          batch: int | None = None) -> Neighbours:
    """Neighbourhoods ``B(s0, g0)`` of a batch of queries: pure and jittable.

    ``query_s [Q, d_s]``, ``query_g`` ``None`` / ``[Q]`` / ``[Q, d_g]`` as the data's goals.
    Returns :class:`lazyq_jax.neighbours.Neighbours` with ``idx [Q, k]``, ``level [Q]``
    (``-1``: none within ``max_level``) and ``count [Q] = |B_level|``.  ``batch``
    queries share one pass (``lax.map``); default 1 on a CPU (measured at N = 1M, d_s =
    5: 14 ms a query one at a time, 21 ms in batches of 16) and 16 on accelerators.
    """
    if batch is None:
        batch = 1 if jax.default_backend() == "cpu" else 16
    query_s = jnp.asarray(query_s, jnp.float32)
    if query_s.ndim != 2 or query_s.shape[1] != index.d_s:
        raise ValueError(f"query_s must be [Q, {index.d_s}], got {query_s.shape}")
    q = query_s.shape[0]
    if index.goal == "none":
        if query_g is not None:
            raise ValueError("the data have no goals; pass query_g=None")
        cols = query_s
    elif index.goal == "angle":
        if query_g is None or jnp.shape(query_g) != (q,):
            raise ValueError(f"the data goals are angles: query_g must be [{q}], got "
                             f"{None if query_g is None else jnp.shape(query_g)}")
        cols = jnp.concatenate([query_s, wrap_angle(jnp.asarray(query_g, jnp.float32))[:, None]], 1)
    else:
        d_g = index.cols.shape[0] - index.d_s
        if query_g is None or jnp.shape(query_g) != (q, d_g):
            raise ValueError(f"the data goals are vectors: query_g must be [{q}, {d_g}], got "
                             f"{None if query_g is None else jnp.shape(query_g)}")
        cols = jnp.concatenate([query_s, jnp.asarray(query_g, jnp.float32)], 1)
    keys = jax.random.split(key, q)
    idx, level, count = jax.lax.map(lambda a: _one(index, *a), (keys, cols), batch_size=min(batch, q))
    return Neighbours(idx=idx, level=level, count=count)
