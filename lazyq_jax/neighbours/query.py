"""Jittable neighbourhood queries in general spaces, for small batches (a policy step).

:func:`lazyq_jax.neighbours.nd.find_neighbours_nd` answers all of a dataset's queries
at once (host-driven passes, growth without limit).  A policy acting in a ``lax.scan``
rollout needs the same neighbourhoods ``B(s0, g0)`` (§V-A-2, semantics of
:mod:`lazyq_jax.neighbours.nd`: the float32 membership formula, the smallest level
``L <= max_level`` with ``|B_L| >= k``, ``k`` distinct members drawn uniformly) for a
batch of queries at a time, inside ``jit``.  Two engines:

* :func:`build_policy_index` once per dataset, then :func:`query_policy` at every step
  (pure, jittable, vmappable over stacked seeds): a grid over a few selective axes
  whose per-query work is a stencil of cells with static capacities.
* :func:`build_scan_index` / :func:`query_neighbours_scan`: every query scans all
  ``N`` points (``O(N (d_s + d_g))`` a query, no layout; the reference, and the
  policy index's fallback).

The policy index
----------------
*Layout* (host, :func:`build_policy_index`).  The data are sorted by the cell key of
``m <= 4`` grid axes (chosen by a cost model, as :mod:`lazyq_jax.neighbours.nd`, but for
the stencils of the levels a policy query evaluates, not level 0), with a dense table
of cell offsets.  The cells of a non-periodic axis are a power of two wide and start at
a multiple of their width, so a query's cell and its fraction, ``floor(x / w)`` and
``x / w - floor(x / w)``, are exact in float32 under ``jit`` (as the host's float64
cells of the data); the angle's cells tile the circle and carry the angular slack of
:mod:`lazyq_jax.neighbours.nd`.  The stencil of level ``L`` is nd's: one contiguous
range per cell of the non-last axes, the last axis clipped to the chord of the ball;
membership is always the exact float32 formula on all dimensions.

*Phases with static capacities* (``index.phases``, chosen on the host from the data
and ``max_level``).  Phase 0 evaluates levels ``0..h_0`` (one membership word per level
and item) for every query of the batch; the queries with fewer than ``k`` members at
``h_0`` go to phase 1 (levels ``h_0+1..h_1``, the stencil of ``h_1``), in rounds, and so
on up to ``max_level``.  A later phase's round has a pool of ``S_p * cap_p`` items of
``W = 32`` entries, ``S_p = max(8, ceil(frac_p Q))``, shared by ``min(Q, 8 S_p)`` slots
(``_SLOT_FACTOR``), packed smallest stencil first; queries that do not fit wait for the
next round (a ``while_loop``: one round unless the batch is unusual, e.g. far from the
data).  The extra slots are for queries far from the data's pairs, which need high
levels but have small stencils there: pointmaze's evaluation steps took many rounds of a
mostly empty pool with one slot per ``cap_p`` (a trained run's evaluation 70.7 s with
one slot per ``cap_p``, 40.4 s with 8, the same outcomes; queries near the data pay a
little for the slots' ranges and sampling: 0.012 -> 0.015 ms a query on the push task's
data, 0.046 -> 0.053 ms on arm-long's, ``experiments/bench_policy_2d.py``, one run
each).  ``h_p``, ``frac_p`` and
``cap_p`` come from a sample of queries (default: data points moved by about a radius):
the schedule and grid of least estimated work (an extra phase must save 15%: each costs
~2-3 s of compile), ``frac_p`` 1.5x the estimated share still short of ``k`` (+3%),
``cap_p`` 1.1x the 99th percentile of the exact items a query needs (full table).  The
work of a round is therefore bounded by ``S_p cap_p W + 8 S_p ranges_p`` entry tests and
range lookups plus ``8 S_p k (k + log2(S_p cap_p))`` for sampling, whatever its queries
(the layout's cost model still counts ``S_p`` slots).  Measured before the extra slots (N = 1M,
arm-like data, 320 queries, 2 shared cores): d_s = 3 phases 0-4 (320 x 56 items) and 5
(16 x 88): 0.07-0.13 ms a query; d_s = 5 one phase 0-5 (320 x 90): 0.11-0.14 ms; the
scan 11-14 ms (experiments/bench_neighbours_query.py); max_level 10 instead of 5: 0.14
and 0.24 ms, and 0.36-0.57 ms for queries far outside the data (many rounds).

*Overflow* (never silent).  A query whose stencil alone exceeds its phase's pool is
flagged in ``PolicyNeighbours.overflow`` and answered exactly by a scan of all data (a
``while_loop`` over the flagged queries only: no cost when nothing overflows;
``fallback=False`` leaves them ``level == -1``, still flagged).  With the measured
capacities this takes a stencil ``S_p`` times the 99th percentile (never seen outside
forced tiny capacities).  Queries beyond ``max_level`` get ``level == -1``, ``idx == -1``
and ``count = |B_max_level|``.  Non-finite queries have no members: ``level == -1``,
``count == 0`` (and ``ValueError`` outside ``jit``).

*Randomness.*  Query ``q`` (its row) draws from a keyed hash of ``(key, q)`` only: its
sample depends on the key, its row, its coordinates and the layout, not on the other
queries or the round it runs in (the fallback scan draws another, equally uniform,
sample: ``k`` largest hashed keys).

*Padding and seeds.*  ``n_valid``: rows ``>= n_valid`` are never members (padding of
datasets stacked over seeds).  :func:`stack_policy_indices` gives several datasets'
indices one layout (the union of their grids' bounds), the largest capacities and
padded arrays, stacked on a leading axis for ``jax.vmap`` over seeds.

The scan engine costs ``O(N (d_s + d_g))`` a query (11-14 ms at N = 1M on 2 cores).  The
lazy policy uses the policy index in every space, the paper's 2-D states with angle goals
included: there the grid's own jittable query
(:func:`lazyq_jax.neighbours.grid.query_neighbours`, kept as a public function) evaluates
the stencil of ``max_level`` for every query, and the policy index's phases do less
(``experiments/bench_policy_2d.py``).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from lazyq_jax.neighbours.common import (PI, TWO_PI, W, Neighbours, _check_params, _items, _key_words,
                                         _member_words, _mix32, _pick_level, _query_seeds, _sample_members,
                                         _sq, radius_tables, wrap_angle)
from lazyq_jax.neighbours.nd import (MAX_GRID_AXES, GridAxis, _axes_info, _offsets, _points, _query_cells,
                                     _ranges, _sorted_columns, _table, _table_limit, membership_level_reference)

__all__ = ["Phase", "PolicyIndex", "PolicyNeighbours", "ScanIndex", "build_policy_index", "build_scan_index",
           "query_neighbours_scan", "query_policy", "stack_policy_indices"]


@struct.dataclass
class PolicyNeighbours(Neighbours):
    """:class:`~lazyq_jax.neighbours.Neighbours` plus ``overflow [Q]`` (bool): the query's
    stencil alone exceeded a phase's pool (the index's static capacities); its result comes
    from the full scan (exact), or is ``level == -1`` if :func:`query_policy` ran with
    ``fallback=False``.  ``overflow.sum()`` counts the scans a batch paid for."""

    overflow: jax.Array


# ----------------------------------------------------------------------------- shared pieces


def _level_tables(radius_s, radius_g, growth, max_level):
    """float32 thresholds ``(R2S, RG, RG2)`` of levels ``0..max_level``."""
    levels = np.arange(max_level + 1)
    r2s, rg = radius_tables(radius_s, radius_g, growth, levels)
    rg2, _ = radius_tables(radius_g, radius_g, growth, levels)
    return r2s, rg, rg2


_WRAP_TURNS = 256  # |g| up to this many turns: the jitted wrap is bitwise NumPy's wrap_angle


def _wrap_tables():
    """``(T, P)``: ``T[i]`` the smallest float32 ``a`` with ``float32(a / TWO_PI) >= n_i``
    (``n_i = i - _WRAP_TURNS + 1``), ``P[j] = float32(TWO_PI * (j - _WRAP_TURNS))``."""
    n = np.arange(-_WRAP_TURNS + 1, _WRAP_TURNS + 1)
    a = (n.astype(np.float64) * np.float64(TWO_PI)).astype(np.float32)
    for _ in range(4):  # step to the exact float32 threshold (NumPy divides correctly rounded)
        lower = np.nextafter(a, np.float32(-np.inf))
        a = np.where(lower / TWO_PI >= n, lower, a)
        a = np.where(a / TWO_PI >= n, a, np.nextafter(a, np.float32(np.inf)))
    assert ((a / TWO_PI >= n) & (np.nextafter(a, np.float32(-np.inf)) / TWO_PI < n)).all()
    turns = np.arange(-_WRAP_TURNS, _WRAP_TURNS + 1)
    return a.astype(np.float32), (TWO_PI * turns.astype(np.float32)).astype(np.float32)


_WRAP_T, _WRAP_P = _wrap_tables()


def _wrap_jit(g):
    """:func:`~lazyq_jax.neighbours.common.wrap_angle` under ``jit``, bitwise equal to the
    NumPy evaluation for ``|g| < 256 * 2pi`` (XLA turns ``/ TWO_PI`` into a multiply by the
    reciprocal and may fuse ``TWO_PI * f`` into the subtraction; both change last bits at
    the wrap boundaries): ``floor((g + PI) / TWO_PI)`` counts exact thresholds, ``TWO_PI * f``
    is read from a table."""
    a = g + PI
    f = jnp.searchsorted(jnp.asarray(_WRAP_T), a, side="right", method="compare_all")
    return g - jnp.asarray(_WRAP_P)[jnp.clip(f, 0, 2 * _WRAP_TURNS)]


def _entries_at_or_below(table, v):
    """``searchsorted(table, v, side="right")`` for a short sorted float32 table given on the
    host: the number of entries ``<= v``, one fused comparison per entry.  (``searchsorted``'s
    ``compare_all`` broadcasts the table to ``[len, E]``; inside the policy's fallback loop XLA
    hoisted those broadcasts out of the loop, 2 x 36 MB written at every policy step at
    N = 1M whether or not any query fell back: 44 against 15 ms a step of 250 queries.)"""
    out = jnp.zeros(v.shape, jnp.int32)
    for t in np.asarray(table, np.float32):
        out = out + (v >= jnp.float32(t)).astype(jnp.int32)
    return out


def _entry_levels(cols, q, *, d_s, goal, tables):
    """``[E]`` int32: each column's smallest level with the point in ``B_L(q)`` (``len(R2S)``
    if none); ``cols [n_cols, E]``, ``q [n_cols]`` one query."""
    r2s, rg, rg2 = tables
    ds2 = _sq(cols[0] - q[0])
    for i in range(1, d_s):
        ds2 = ds2 + _sq(cols[i] - q[i])
    lam = _entries_at_or_below(r2s, ds2)
    if goal == "angle":
        d = jnp.abs(cols[d_s] - q[d_s])
        lam = jnp.maximum(lam, _entries_at_or_below(rg, jnp.minimum(d, TWO_PI - d)))
    elif goal == "vector":
        dg2 = _sq(cols[d_s] - q[d_s])
        for i in range(d_s + 1, cols.shape[0]):
            dg2 = dg2 + _sq(cols[i] - q[i])
        lam = jnp.maximum(lam, _entries_at_or_below(rg2, dg2))
    return lam


def _query_columns(d_s, goal, d_g, query_s, query_g):
    """Queries as float32 columns ``[n_cols, Q]`` (the angle wrapped); shape errors raise, and
    NaN/inf raise when the queries are concrete (under ``jit`` they have no members)."""
    shape_g = None if query_g is None else jnp.shape(query_g)
    if jnp.ndim(query_s) != 2 or jnp.shape(query_s)[1] != d_s:
        raise ValueError(f"query_s must be [Q, {d_s}] (the data's d_s), got {jnp.shape(query_s)}")
    q = jnp.shape(query_s)[0]
    if goal == "none" and query_g is not None:
        raise ValueError(f"the data have no goals; pass query_g=None (got goals of shape {shape_g})")
    if goal == "angle" and shape_g != (q,):
        raise ValueError(f"the data goals are angles: query_g must be [{q}], got {shape_g}")
    if goal == "vector" and shape_g != (q, d_g):
        raise ValueError(f"the data goals are vectors: query_g must be [{q}, {d_g}], got {shape_g}")
    for name, x in (("query_s", query_s), ("query_g", query_g)):
        if x is not None and not isinstance(x, jax.core.Tracer) and not np.isfinite(np.asarray(x)).all():
            raise ValueError(f"{name} contains NaN or inf; fix those queries (under jit they get level -1)")
    s = jnp.asarray(query_s, jnp.float32).T
    if goal == "none":
        return s
    g = jnp.asarray(query_g, jnp.float32)
    return jnp.concatenate([s, _wrap_jit(g)[None, :] if goal == "angle" else g.T], axis=0)


def _hash_keys(seed, n):
    """``[n]`` int32 in ``[1, 2^31)``: independent uniform sort keys of a query's entries."""
    e = jnp.arange(n, dtype=jnp.uint32)
    h = _mix32(_mix32(e ^ seed) + (seed * jnp.uint32(0x9E3779B9) + jnp.uint32(0x7F4A7C15)))
    return (h >> 1).astype(jnp.int32) | 1


def _scan_sample(lam, valid, seed, k, max_level):
    """From entry levels ``lam [E]``: ``(entries [k], level, count)`` of one query, the
    members drawn as the ``k`` largest hashed keys (a uniform k-subset; ties have
    probability ``~m^2 / 2^31``)."""
    lam = jnp.where(valid, lam, max_level + 1)
    counts = jnp.cumsum(jnp.bincount(lam, length=max_level + 2))[:-1]
    enough = counts >= k
    found = enough.any()
    level = jnp.where(found, jnp.argmax(enough), -1).astype(jnp.int32)
    u = jnp.where((lam <= level) & found, _hash_keys(seed, lam.shape[0]), 0)
    _, ent = jax.lax.top_k(u, k)
    count = jnp.where(found, counts[jnp.maximum(level, 0)], counts[-1])
    return jnp.where(found, ent.astype(jnp.int32), -1), level, count.astype(jnp.int32)


# ----------------------------------------------------------------------------- scan engine


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


def _check_max_level(max_level):
    if not isinstance(max_level, (int, np.integer)) or isinstance(max_level, bool) or max_level < 0:
        raise ValueError(f"max_level must be an int >= 0, got {max_level!r}")


def build_scan_index(data_s, data_g=None, *, k=20, radius_s=0.06, radius_g=0.1, growth=2 ** (1 / 3),
                     max_level=8) -> ScanIndex:
    """Validate the data (shapes, NaN/inf, ``k <= N``) and keep its columns for queries."""
    _check_params(k, radius_s, radius_g, growth)
    _check_max_level(max_level)
    cols, d_s, kind, _ = _points(data_s, data_g, "data")
    if cols.shape[1] < k:
        raise ValueError(f"need at least k={k} data points to draw k distinct neighbours, got {cols.shape[1]}")
    return ScanIndex(jnp.asarray(cols), int(k), float(radius_s), float(radius_g), float(growth), d_s, kind,
                     int(max_level))


def entry_levels(index: ScanIndex, q):
    """``[N]`` int32: each data point's smallest level ``L <= max_level`` with the point in
    ``B_L(q)`` (``max_level + 1`` if none); ``q [d_s + d_g]`` one query's columns."""
    return _entry_levels(index.cols, q, d_s=index.d_s, goal=index.goal,
                         tables=_level_tables(index.radius_s, index.radius_g, index.growth, index.max_level))


def _one(index: ScanIndex, key, q):
    lam = entry_levels(index, q)
    # |B_L| for every L: a histogram of the entry levels, summed up (O(N), not O(levels N)).
    counts = jnp.cumsum(jnp.bincount(lam, length=index.max_level + 2))[:-1]
    enough = counts >= index.k
    found = enough.any()
    level = jnp.where(found, jnp.argmax(enough), -1).astype(jnp.int32)
    u = jax.random.uniform(key, lam.shape, minval=0.5, maxval=1.0)  # members: keys > 0
    _, idx = jax.lax.top_k(jnp.where((lam <= level) & found, u, 0.0), index.k)
    count = jnp.where(found, counts[jnp.maximum(level, 0)], counts[-1])
    return jnp.where(found, idx.astype(jnp.int32), -1), level, count.astype(jnp.int32)


def query_neighbours_scan(index: ScanIndex, key, query_s, query_g=None, *,
                          batch: int | None = None) -> Neighbours:
    """Neighbourhoods ``B(s0, g0)`` of a batch of queries by a scan of all data: pure and jittable.

    ``query_s [Q, d_s]``, ``query_g`` ``None`` / ``[Q]`` / ``[Q, d_g]`` as the data's goals.
    Returns :class:`lazyq_jax.neighbours.Neighbours` with ``idx [Q, k]``, ``level [Q]``
    (``-1``: none within ``max_level``; then ``idx == -1`` and ``count = |B_max_level|``)
    and ``count [Q] = |B_level|``.  ``batch`` queries share one pass (``lax.map``);
    default 1 on a CPU (measured at N = 1M, d_s = 5: 14 ms a query one at a time, 21 ms
    in batches of 16) and 16 on accelerators.
    """
    if batch is None:
        batch = 1 if jax.default_backend() == "cpu" else 16
    d_g = index.cols.shape[0] - index.d_s
    cols = _query_columns(index.d_s, index.goal, d_g, query_s, query_g).T
    q = cols.shape[0]
    keys = jax.random.split(key, q)
    idx, level, count = jax.lax.map(lambda a: _one(index, *a), (keys, cols), batch_size=max(min(batch, q), 1))
    return Neighbours(idx=idx, level=level, count=count)


# ----------------------------------------------------------------------------- policy index


@dataclass(frozen=True)
class Phase:
    """One static phase of :func:`query_policy`: levels ``lo..hi`` (the stencil of ``hi``); a
    later phase's round holds ``slots(Q) * cap`` items, shared by ``_SLOT_FACTOR * slots(Q)``
    queries (at most ``Q``)."""

    lo: int
    hi: int
    frac: float  # slots a batch of Q queries: Q in phase 0, else min(Q, max(min_slots, ceil(frac Q)))
    min_slots: int
    cap: int  # items (W entries) per slot

    def slots(self, q: int) -> int:
        if self.lo == 0:
            return q
        return min(q, max(self.min_slots, math.ceil(self.frac * q - 1e-9)))


@struct.dataclass
class PolicyIndex:
    """Data sorted by grid cell, static capacities (see module docstring); build with
    :func:`build_policy_index`, stack seeds with :func:`stack_policy_indices`."""

    cols: jax.Array  # float32 [n_cols, E + W]: sorted entries (states, wrapped angle / goal dims)
    orig: jax.Array  # int32 [E]: data row of each entry
    offsets: jax.Array  # int32 [n_cells + 1]: first entry of each cell
    n_entries: jax.Array  # int32 []: entries of this dataset (E, or fewer when padded for stacking)
    k: int = struct.field(pytree_node=False)
    radius_s: float = struct.field(pytree_node=False)
    radius_g: float = struct.field(pytree_node=False)
    growth: float = struct.field(pytree_node=False)
    d_s: int = struct.field(pytree_node=False)
    goal: str = struct.field(pytree_node=False)  # "angle" | "vector" | "none"
    d_g: int = struct.field(pytree_node=False)
    max_level: int = struct.field(pytree_node=False)
    n_rows: int = struct.field(pytree_node=False)  # rows of the (padded) dataset: idx < n_rows
    grid: tuple = struct.field(pytree_node=False)  # tuple[GridAxis]; () = scan every query
    phases: tuple = struct.field(pytree_node=False)  # tuple[Phase]; () with grid ()


_MIN_SLOTS = 8
_REF_BATCH = 320  # batch size the cost model assumes (a rollout's episodes)
_CAP_QUANTILE = 99.0
_CAP_MARGIN = 1.1
_SLOT_MARGIN, _SLOT_EXTRA = 1.5, 0.03
_RANGE_COST = 0.25  # items' worth of work a stencil range costs
_SLOT_COST = 4.0  # items' worth of work a slot costs beyond its items (sampling)
_PHASE_COST = 0.15  # an extra phase must save 15% (each adds ~2-3 s of compile on a 2-core CPU)
_N_SAMPLE = 512  # sample queries for capacities
_N_EST = 256  # sample queries for the level and cost estimates
_EST_SUB = 1 << 16  # data subsample of the estimates


def _sample_rows(rng, n, m):
    return np.sort(rng.choice(n, m, replace=False)) if n > m else np.arange(n)


def _axis_p2(col, block, periodic, radius, width, lo, hi):
    """A grid axis of about ``width``: a power of two starting at a multiple of it (exact cells
    under jit), or ``n`` cells tiling the circle (the angle)."""
    if periodic:
        n = max(1, math.floor(2 * math.pi / width + 1e-9))
        return GridAxis(col, block, True, -math.pi, 2 * math.pi / n, n, radius)
    w = 2.0 ** round(math.log2(width))
    c0, c1 = math.floor(lo / w), math.floor(hi / w)
    return GridAxis(col, block, False, c0 * w, w, c1 - c0 + 1, radius)


def _make_grid(axes, widths, col_lo, col_hi, n_limit):
    """Grid of ``axes`` (``(col, block, periodic, radius)``) with about ``widths`` (raw units),
    all widths doubled until the offset table has at most ``n_limit`` cells."""
    for _ in range(200):
        grid = tuple(_axis_p2(*a, w, col_lo[a[0]], col_hi[a[0]]) for a, w in zip(axes, widths))
        if math.prod(ax.n for ax in grid) <= n_limit:
            return grid
        widths = [2 * w for w in widths]
    raise AssertionError("internal error: no grid fits the table limit")


def _estimate_levels(cols, qcols, d_s, kind, radius_s, radius_g, growth, k, max_level, rng):
    """Each sample query's level (``max_level + 1``: beyond) estimated from a subsample of the
    data (counts scaled up): guides the speed of the layout only, never results."""
    n = cols.shape[1]
    sub = cols[:, _sample_rows(rng, n, _EST_SUB)]
    scale = n / sub.shape[1]

    def split(c):
        g = None if kind == "none" else (c[d_s] if kind == "angle" else c[d_s:].T)
        return c[:d_s].T, g

    ds, dg = split(sub)
    out = []
    for i in range(0, qcols.shape[1], 16):
        qs, qg = split(qcols[:, i:i + 16])
        lam = membership_level_reference(ds, dg, qs, qg, radius_s=radius_s, radius_g=radius_g, growth=growth,
                                         max_level=max_level)
        counts = np.stack([(lam <= lv).sum(1) for lv in range(max_level + 1)], axis=1) * scale
        enough = counts >= k
        out.append(np.where(enough.any(1), np.argmax(enough, axis=1), max_level + 1))
    return np.concatenate(out)


def _needs(grid, offsets, qcols, level, growth, scale=1.0):
    """Items (of ``W`` entries) each query's level-``level`` stencil needs: exact with the full
    table (``scale`` 1), estimated from a subsample's table otherwise."""
    ip, fr, _ = _query_cells(grid, qcols)
    _, length, _ = _ranges(np, grid, offsets, ip.astype(np.int64), fr, level, growth)
    return np.ceil(length * scale / W).sum(axis=1)


def _n_ranges(grid, level, growth):
    return int(np.prod([ax.enum(level, growth)[0] for ax in grid[:-1]], dtype=np.int64)) if grid else 1


def _fractions(his, levels):
    """Slot fraction of each phase after the first: 1.5x the estimated share of queries still
    short of ``k`` after the previous phase, +3%."""
    return [1.0] + [min(1.0, _SLOT_MARGIN * float(np.mean(levels > h)) + _SLOT_EXTRA) for h in his[:-1]]


def _schedule_cost(grid, his, fracs, need_q, growth, n_entries):
    """Work per query (in items) of a schedule: every phase's pool, ranges and slots."""
    cost = 0.0
    for hi, frac in zip(his, fracs):
        r = _n_ranges(grid, hi, growth)
        if r * 4 * W > max(n_entries, 4 * W):  # more ranges than a scan has items
            return math.inf
        slots = 1.0 if frac == 1.0 else min(1.0, max(_MIN_SLOTS / _REF_BATCH, frac))
        cost += slots * (_CAP_MARGIN * need_q[hi] + _RANGE_COST * r + _SLOT_COST)
    return cost * (1 + _PHASE_COST * (len(his) - 1))


def _candidate_schedules(levels, max_level):
    """Phase top levels: one phase, or phases ending where 50..97% of the sample stops."""
    qs = sorted({int(min(np.percentile(levels, p, method="higher"), max_level)) for p in (50, 75, 90, 97)})
    out = [(max_level,)] + [(h, max_level) for h in qs if h < max_level]
    out += [(a, b, max_level) for a in qs for b in qs if a < b < max_level]
    return out


def _choose_layout(cols, d_s, kind, d_g, radius_s, radius_g, growth, max_level, k, qcols, col_lo, col_hi, rng):
    """Cheapest ``(grid, phase top levels)`` by :func:`_schedule_cost` on a data subsample, over
    axis prefixes (by selectivity at the typical level), power-of-two cell widths and the
    schedules of :func:`_candidate_schedules`; ``((), ())`` if a scan is cheaper."""
    n = cols.shape[1]
    est_q = qcols[:, _sample_rows(rng, qcols.shape[1], _N_EST)]
    levels = _estimate_levels(cols, est_q, d_s, kind, radius_s, radius_g, growth, k, max_level, rng)
    schedules = _candidate_schedules(levels, max_level)
    h_ref = int(min(np.median(levels), max_level))
    sub = cols[:, _sample_rows(rng, n, _EST_SUB)]
    scale = n / sub.shape[1]
    info = _axes_info(d_s, kind, d_g, radius_s, radius_g)
    sel = []
    for col, _block, periodic, radius in info:  # fraction of the data within the typical radius
        x = np.sort(sub[col].astype(np.float64))
        r = radius * growth**h_ref
        if periodic:
            x = np.concatenate([x - 2 * np.pi, x, x + 2 * np.pi])
        q = est_q[col].astype(np.float64)
        sel.append(float(((np.searchsorted(x, q + r) - np.searchsorted(x, q - r)) / sub.shape[1]).mean()))
    order = [info[i] for i in np.argsort(sel, kind="stable")]
    best, best_cost = ((), ()), n / W + _SLOT_COST  # the scan
    seen = set()
    for m in range(1, min(MAX_GRID_AXES, len(order)) + 1):
        axes = order[:m]
        axes = [a for a in axes if a[2]] + [a for a in axes if not a[2]]  # periodic first
        if axes[-1][2]:
            continue  # the contiguous (last) axis must not be periodic
        for h_other in (0.5, 1.0, 2.0):
            for h_last in (0.25, 0.5, 1.0):
                if h_last > h_other or (m == 1 and h_other != 1.0):
                    continue
                widths = [(h_other if j < m - 1 else h_last) * a[3] * growth**h_ref for j, a in enumerate(axes)]
                grid = _make_grid(axes, widths, col_lo, col_hi, _table_limit(n))
                if grid in seen:
                    continue
                seen.add(grid)
                offsets = _offsets(grid, _table(grid, sub)[0])
                need_q = {}
                for sched in schedules:
                    for h in sched:
                        if h not in need_q:
                            need_q[h] = float(np.percentile(_needs(grid, offsets, est_q, h, growth, scale),
                                                            _CAP_QUANTILE))
                    cost = _schedule_cost(grid, sched, _fractions(sched, levels), need_q, growth, n)
                    if cost < best_cost * 0.98:
                        best, best_cost = (grid, sched), cost
    return best[0], best[1], levels


def _check_data(data_s, data_g, n_valid):
    """Shapes of the full (padded) arrays; validated columns of the first ``n_valid`` rows."""
    s = np.asarray(data_s)
    if s.ndim != 2:
        raise ValueError(f"data_s must have shape [N, d_s], got {s.shape}")
    n_rows = s.shape[0]
    g = None if data_g is None else np.asarray(data_g)
    if g is not None and (g.ndim not in (1, 2) or g.shape[0] != n_rows):
        raise ValueError(f"data_g must be None, an angle [{n_rows}] or a vector [{n_rows}, d_g] to match "
                         f"data_s {s.shape}, got {g.shape}")
    if n_valid is None:
        n_valid = n_rows
    if isinstance(n_valid, bool) or not isinstance(n_valid, (int, np.integer)) or not 0 <= n_valid <= n_rows:
        raise ValueError(f"n_valid must be an int in [0, {n_rows}] (rows >= n_valid are padding), got {n_valid!r}")
    cols, d_s, kind, d_g = _points(s[:n_valid], None if g is None else g[:n_valid], "data")
    return cols, d_s, kind, d_g, n_rows


def _parse_schedule(schedule, max_level):
    """``schedule``: phase top levels ``(h_0, ..., max_level)``, each optionally ``(h, frac)``."""
    message = (f"schedule must list increasing phase top levels ending at max_level={max_level}, each an "
               f"int or (level, slot fraction in (0, 1]), got {schedule!r}")
    his, fracs = [], []
    try:
        for item in schedule:
            h, f = (item, None) if isinstance(item, (int, np.integer)) else tuple(item)
            if isinstance(h, bool) or not isinstance(h, (int, np.integer)):
                raise ValueError(message)  # noqa: TRY004 (one error type)
            his.append(int(h))
            fracs.append(None if f is None else float(f))
    except (TypeError, ValueError) as e:
        raise ValueError(message) from e
    if (not his or his[-1] != max_level or any(b <= a for a, b in itertools.pairwise(his)) or his[0] < 0
            or any(f is not None and not 0 < f <= 1 for f in fracs)):
        raise ValueError(message)
    return tuple(his), fracs


def _layout(cols, n_rows, *, params, grid, his, fracs, capacity, qcols):
    """The arrays and phases of one dataset on a given layout (``grid`` ``()``: scan only)."""
    k, radius_s, radius_g, growth, d_s, kind, d_g, max_level = params
    n = cols.shape[1]
    src, offsets, sorted_cols = _sorted_columns(grid, cols)
    phases = []
    if grid:
        caps = list(capacity) if isinstance(capacity, (tuple, list)) else [capacity] * len(his)
        lo = 0
        for hi, frac, cap in zip(his, fracs, caps):
            if cap is None:
                need = _needs(grid, offsets, qcols, hi, growth)
                cap = max(1, math.ceil(_CAP_MARGIN * float(np.percentile(need, _CAP_QUANTILE))))
            phases.append(Phase(lo, hi, 1.0 if lo == 0 else frac, _MIN_SLOTS, int(cap)))
            lo = hi + 1
    # Cells of non-periodic axes as int32 under jit (with the clamp margin of _cells).
    for ax in grid:
        if not ax.periodic and abs(ax.origin / ax.width) + ax.n + ax.span(max_level, growth) + 4 > 2**30:
            raise ValueError(f"data column {ax.col} spans too many cells of width {ax.width} (radius too small "
                             "for the coordinates' magnitude)")
    return PolicyIndex(
        cols=jnp.asarray(sorted_cols), orig=jnp.asarray(src.astype(np.int32)),
        offsets=jnp.asarray(offsets.astype(np.int32)), n_entries=jnp.int32(n), k=int(k),
        radius_s=float(radius_s), radius_g=float(radius_g), growth=float(growth), d_s=d_s, goal=kind, d_g=d_g,
        max_level=int(max_level), n_rows=int(n_rows), grid=tuple(grid), phases=tuple(phases))


def _parse_capacity(capacity, his):
    """``None``, a positive int, or (with a ``schedule``) one per phase (``None``: measured)."""
    def ok(c):
        return c is None or (isinstance(c, (int, np.integer)) and not isinstance(c, bool) and c >= 1)

    if isinstance(capacity, (tuple, list)):
        if his is None or len(capacity) != len(his) or not all(ok(c) for c in capacity):
            raise ValueError(f"capacity per phase needs schedule= and one positive int (or None) per phase "
                             f"({'no schedule' if his is None else len(his)}), got {capacity!r}")
        return list(capacity)
    if not ok(capacity):
        raise ValueError(f"capacity must be a positive int (items of {W} entries a slot), got {capacity!r}")
    return capacity


def _default_sample(cols, d_s, kind, radius_s, radius_g, rng, m):
    """Data points moved by about a radius (sd radius/2 a dimension): queries between the data,
    like a rollout's (data points themselves would count their own copies)."""
    q = cols[:, _sample_rows(rng, cols.shape[1], m)].astype(np.float64)
    q[:d_s] += rng.normal(0, radius_s / 2, (d_s, q.shape[1]))
    if kind != "none":
        q[d_s:] += rng.normal(0, radius_g / 2, (q.shape[0] - d_s, q.shape[1]))
    q = q.astype(np.float32)
    if kind == "angle":
        q[d_s] = wrap_angle(q[d_s])
    return q


def build_policy_index(data_s, data_g=None, *, k, radius_s, radius_g, growth, max_level, n_valid=None,
                       query_sample=None, grid=None, schedule=None, capacity=None, seed=0,
                       stats: dict | None = None) -> PolicyIndex:
    """Sort the data into the policy's grid and fix its static capacities (host, NumPy).

    ``data_s [N, d_s]`` (``1 <= d_s <= 10``), ``data_g`` ``None`` / angles ``[N]`` / vectors
    ``[N, d_g]``; rows ``>= n_valid`` are padding, never members (default: none; they may
    hold anything).  ``max_level``: the most growths a query may use (beyond: ``level == -1``).
    ``query_sample``: ``(query_s, query_g)`` like the policy's queries, to tune the layout and
    capacities for (default: data points moved by about a radius).  Overrides (tests,
    tuning): ``grid`` a sequence of ``(axis, width)`` (axis ``0..d_s-1`` a state dim,
    ``d_s..`` the goal dims, width in raw units, rounded to a power of two; the last axis not
    the angle), ``()`` for scan only; ``schedule`` the phases' top levels ``(h_0, ...,
    max_level)``, each optionally ``(h, slot fraction)``; ``capacity`` items (of ``W``
    entries) a slot, an int or (with ``schedule``) one per phase.  ``stats``: filled with the
    layout and the sample's estimated levels.  The choices change speed only, never results.

    Raises ``ValueError`` for bad shapes, NaN/inf in the valid rows, ``k > n_valid``, bad
    radii, growth, max_level or overrides.  Measured: 0.6-1 s at N = 1M (d_s = 3-5, angle
    goals) on 2 shared cores.
    """
    _check_params(k, radius_s, radius_g, growth)
    _check_max_level(max_level)
    cols, d_s, kind, d_g, n_rows = _check_data(data_s, data_g, n_valid)
    n = cols.shape[1]
    if n < k:
        raise ValueError(f"need at least k={k} valid data points to draw k distinct neighbours, got {n}")
    if growth**max_level > 1e12:
        raise ValueError(f"growth**max_level = {growth ** max_level:.3g}: max_level={max_level} is too large")
    his, fracs = _parse_schedule(schedule, max_level) if schedule is not None else (None, None)
    capacity = _parse_capacity(capacity, his)
    params = (int(k), float(radius_s), float(radius_g), float(growth), d_s, kind, d_g, int(max_level))
    rng = np.random.default_rng(seed)
    if query_sample is not None:
        qc, qd_s, qkind, qd_g = _points(*query_sample, "query")
        if (qd_s, qkind, qd_g) != (d_s, kind, d_g):
            raise ValueError(f"query_sample ({qkind} goals, d_s={qd_s}, d_g={qd_g}) does not match the data "
                             f"({kind}, d_s={d_s}, d_g={d_g})")
        qcols = qc[:, _sample_rows(rng, qc.shape[1], _N_SAMPLE)] if qc.shape[1] else None
    else:
        qcols = None
    if qcols is None:
        qcols = _default_sample(cols, d_s, kind, radius_s, radius_g, rng, _N_SAMPLE)
    col_lo, col_hi = cols.min(axis=1).astype(np.float64), cols.max(axis=1).astype(np.float64)
    levels = None
    if grid is None:
        chosen, auto_his, levels = _choose_layout(cols, d_s, kind, d_g, radius_s, radius_g, growth, max_level, k,
                                                  qcols, col_lo, col_hi, rng)
    else:
        chosen, auto_his = _forced_grid(grid, d_s, kind, d_g, radius_s, radius_g, col_lo, col_hi, n), (max_level,)
    if chosen and his is None:
        his, fracs = auto_his, [None] * len(auto_his)
    if chosen:
        if levels is None and any(f is None for f in fracs[1:]):
            levels = _estimate_levels(cols, qcols[:, :_N_EST], d_s, kind, radius_s, radius_g, growth, k,
                                      max_level, rng)
        auto = _fractions(his, levels) if levels is not None else [1.0] * len(his)
        fracs = [a if f is None else f for a, f in zip(auto, fracs)]
    else:
        his, fracs = (), []
    index = _layout(cols, n_rows, params=params, grid=chosen, his=his, fracs=fracs, capacity=capacity,
                    qcols=qcols)
    if stats is not None:
        stats.update(grid=index.grid, phases=index.phases,
                     levels=None if levels is None else np.bincount(levels, minlength=max_level + 2))
    return index


def _forced_grid(spec, d_s, kind, d_g, radius_s, radius_g, col_lo, col_hi, n):
    info = _axes_info(d_s, kind, d_g, radius_s, radius_g)
    message = (f"grid must list at most {MAX_GRID_AXES} distinct axes in [0, {len(info)}) as (axis, width) "
               f"with finite positive widths, got {spec!r}")
    try:
        spec = [(a, float(w)) for a, w in spec]
    except (TypeError, ValueError) as e:
        raise ValueError(message) from e
    if any(isinstance(a, bool) or not isinstance(a, (int, np.integer)) for a, _ in spec):
        raise ValueError(message)
    if (len(spec) > MAX_GRID_AXES or any(not 0 <= a[0] < len(info) for a in spec)
            or len({a[0] for a in spec}) != len(spec) or any(not 0 < a[1] < math.inf for a in spec)):
        raise ValueError(message)
    if spec and info[spec[-1][0]][2]:
        raise ValueError("the last grid axis must not be the (periodic) angle")
    if not spec:
        return ()
    return _make_grid([info[a[0]] for a in spec], [float(a[1]) for a in spec], col_lo, col_hi, _table_limit(n))


def _data_of(index: PolicyIndex):
    """The valid rows' columns ``[n_cols, n_valid]`` back from an index (rows ``0..n_valid-1``)."""
    e = int(index.n_entries)
    orig = np.asarray(index.orig)[:e]
    cols = np.empty((index.cols.shape[0], e), np.float32)
    cols[:, orig] = np.asarray(index.cols)[:, :e]
    return cols


_SETTINGS = ("k", "radius_s", "radius_g", "growth", "d_s", "goal", "d_g", "max_level")


def _pow2(n: int) -> int:
    return 1 << max(int(n) - 1, 0).bit_length()


def stack_policy_indices(indices, *, seed=0, like: PolicyIndex | None = None) -> PolicyIndex:
    """Several datasets' indices as one, arrays stacked on a leading axis, for ``jax.vmap``
    over seeds (``jax.vmap(query_policy, in_axes=(0, 0, 0, 0))``).

    All must share ``k``, radii, growth, ``max_level``, the space and ``n_rows`` (pad the
    datasets to one length, with ``n_valid``).  Indices on different grids are laid out again
    on one grid: the first's axes and widths over the union of their bounds, the first's
    phase levels (host; a sort per dataset).  Every capacity and slot fraction is raised to
    the largest, the entry arrays padded (padding entries are never read).  A stacked
    query equals each dataset's own query on the common layout (tests check this).

    The entry arrays are padded to the datasets' rows (``n_rows``), so an index keeps its
    shapes while its dataset fills the padding rows.  ``like``: an earlier index (stacked or
    not, or its shapes: ``jax.ShapeDtypeStruct`` leaves) whose compiled queries should serve
    the new one too, e.g. a rollout jitted for the policy of the previous online round.
    Where the stacked layout (settings, grid and phase levels, which the data choose) is
    ``like``'s, no capacity, slot fraction or entry count falls below ``like``'s, and a
    capacity that must grow is rounded up to a power of two; elsewhere ``like`` is ignored
    (new shapes: the query compiles again).
    Capacities bound the work of a query, not its result, so the result is the same with or
    without ``like`` (it depends on the data, not on earlier calls), except for a query whose
    stencil overflows the smaller capacities: the fallback scan answers it with another
    uniform sample (never seen at the measured capacities).
    """
    indices = list(indices)
    if not indices or not all(isinstance(i, PolicyIndex) for i in indices):
        raise ValueError("stack_policy_indices needs a non-empty list of PolicyIndex")
    if any(np.ndim(i.n_entries) != 0 for i in indices):
        raise ValueError("stack_policy_indices takes single-dataset indices (already stacked: one has a seed axis)")
    first = indices[0]
    for name in (*_SETTINGS, "n_rows"):
        values = [getattr(i, name) for i in indices]
        if any(v != values[0] for v in values):
            raise ValueError(f"indices differ in {name} ({values}); build them with the same settings (pad the "
                             "datasets to one length and pass n_valid)")
    same = all(i.grid == first.grid and [(p.lo, p.hi) for p in i.phases] == [(p.lo, p.hi) for p in first.phases]
               for i in indices)
    if not same:
        datas = [_data_of(i) for i in indices]
        lo = np.min([d.min(axis=1) for d in datas], axis=0).astype(np.float64)
        hi = np.max([d.max(axis=1) for d in datas], axis=0).astype(np.float64)
        if first.grid:
            info = {a[0]: a for a in _axes_info(first.d_s, first.goal, first.d_g, first.radius_s, first.radius_g)}
            n_max = max(d.shape[1] for d in datas)
            grid = _make_grid([info[ax.col] for ax in first.grid], [ax.width for ax in first.grid], lo, hi,
                              _table_limit(n_max))
        else:
            grid = ()
        his = tuple(p.hi for p in first.phases)
        params = (first.k, first.radius_s, first.radius_g, first.growth, first.d_s, first.goal, first.d_g,
                  first.max_level)
        rng = np.random.default_rng(seed)
        rebuilt = []
        for index, data in zip(indices, datas):
            if index.grid == grid and [p.hi for p in index.phases] == list(his):
                rebuilt.append(index)
                continue
            q = _default_sample(data, first.d_s, first.goal, first.radius_s, first.radius_g, rng, _N_SAMPLE)
            fracs = [p.frac for p in first.phases]
            rebuilt.append(_layout(data, index.n_rows, params=params, grid=grid, his=his, fracs=fracs,
                                   capacity=None, qcols=q))
        indices = rebuilt
        first = indices[0]
    if like is not None and not (isinstance(like, PolicyIndex) and like.grid == first.grid
                                 and all(getattr(like, f) == getattr(first, f) for f in _SETTINGS)
                                 and [(p.lo, p.hi) for p in like.phases] == [(p.lo, p.hi) for p in first.phases]):
        like = None

    def widest(j, field):
        need = max(getattr(i.phases[j], field) for i in indices)
        if like is None:
            return need
        old = getattr(like.phases[j], field)
        return old if need <= old else (_pow2(need) if field == "cap" else need)

    phases = tuple(Phase(p.lo, p.hi, *(widest(j, f) for f in ("frac", "min_slots", "cap")))
                   for j, p in enumerate(first.phases))
    # Entries padded to the rows of the (padded) datasets: the shapes do not change while a
    # dataset fills its rows (online rounds), only when the rows or the layout change.
    e = max([int(i.orig.shape[0]) for i in indices] + [first.n_rows]
            + ([int(like.orig.shape[-1])] if like is not None else []))

    def pad(i):
        extra = e - int(i.orig.shape[0])
        return i.replace(cols=jnp.pad(i.cols, ((0, 0), (0, extra))), orig=jnp.pad(i.orig, (0, extra)), phases=phases)

    padded = [pad(i) for i in indices]
    return jax.tree.map(lambda *x: jnp.stack(x), *padded)


# ----------------------------------------------------------------------------- policy query (jit)


def _cells(index: PolicyIndex, qcols):
    """Each query's cell ``ip`` (int32 ``[m, Q]``) and fraction ``fr`` (float32) on every grid
    axis, exact on the power-of-two axes (see module docstring)."""
    ips, frs = [], []
    one = np.float32(1) - np.float32(2.0**-24)
    for ax in index.grid:
        x = qcols[ax.col]
        if ax.periodic:
            u = (x + PI) * jnp.float32(ax.n / (2 * math.pi))
            f = jnp.floor(u)
            ips.append(f.astype(jnp.int32))
        else:
            c0 = round(ax.origin / ax.width)
            margin = ax.span(index.max_level, index.growth) + 2
            lo, hi = (c0 - margin) * ax.width, (c0 + ax.n + margin) * ax.width
            y = jnp.clip(x, jnp.float32(lo), jnp.float32(hi)) * jnp.float32(1.0 / ax.width)  # exact: 2^j
            f = jnp.floor(y)
            u = y
            ips.append(f.astype(jnp.int32) - jnp.int32(c0))
        frs.append(jnp.clip(u - f, 0.0, one))
    return jnp.stack(ips), jnp.stack(frs)


_SLOT_FACTOR = 8  # slots of a later phase's round per S_p of its pool (module docstring)


def _phase(index: PolicyIndex, seeds, real, qcols, ip, fr, phase: Phase, n_slots: int, cap: int):
    """Levels ``phase.lo..phase.hi`` for ``n_slots`` queries sharing ``cap`` items (packed
    smallest stencil first).

    Returns ``(idx, level, count, fit, hopeless)``; ``level == -1`` where ``|B_hi| < k``
    (``count`` then ``|B_hi|``).  Only rows that ``fit`` hold a result; the others may fit
    a later round, except ``hopeless`` ones (a stencil above the whole pool).
    """
    k = index.k
    start, length, bad = _ranges(jnp, index.grid, index.offsets, ip, fr, phase.hi, index.growth)
    length = jnp.where(real[:, None], length, 0)
    need = jnp.sum((length + W - 1) // W, axis=1)
    order = jnp.argsort(need, stable=True)  # pack the smallest needs first: most queries fit
    hopeless = real & ((need > cap) | bad)
    fits = jnp.zeros(n_slots, bool).at[order].set(jnp.cumsum(need[order]) <= cap)
    fits = real & fits & ~hopeless
    length = jnp.where(fits[:, None], length, 0)
    start, length = start[order], length[order]
    qc, sd = qcols[:, order], seeds[order]
    item_q, item_start, item_valid, first, n_q = _items(start, length, cap)
    words = _member_words(index, qc, item_q, item_start, item_valid, phase.lo, phase.hi)
    found, li, level, m = _pick_level(words, item_q, n_slots, k, phase.lo)
    idx = _sample_members(index.orig, words, li, found, m, sd, item_q, item_start, first, n_q, k=k,
                          steps=max(cap.bit_length(), 1))
    inv = jnp.zeros(n_slots, jnp.int32).at[order].set(jnp.arange(n_slots, dtype=jnp.int32))
    return idx[inv], level.astype(jnp.int32)[inv], m.astype(jnp.int32)[inv], fits, hopeless


def _scan_query(index: PolicyIndex, seed, q):
    """The exact result of one query by a scan of all entries (the fallback)."""
    e = index.orig.shape[0]
    lam = _entry_levels(index.cols[:, :e], q, d_s=index.d_s, goal=index.goal,
                        tables=_level_tables(index.radius_s, index.radius_g, index.growth, index.max_level))
    valid = jnp.arange(e) < index.n_entries
    ent, level, count = _scan_sample(lam, valid, seed, index.k, index.max_level)
    return jnp.where(ent >= 0, index.orig[jnp.maximum(ent, 0)], -1), level, count


def query_policy(index: PolicyIndex, key, query_s, query_g=None, *, fallback=True) -> PolicyNeighbours:
    """Neighbourhoods ``B(s0, g0)`` of a batch of queries from a :class:`PolicyIndex`: pure,
    jittable and vmappable (over seeds: :func:`stack_policy_indices`).

    ``query_s [Q, d_s]``, ``query_g`` ``None`` / ``[Q]`` / ``[Q, d_g]`` as the data's goals.
    Static: the index's layout and capacities and the batch size ``Q`` (one compile per
    ``Q``); traced: the index arrays, the key, the queries (and ``fallback``).
    Returns :class:`PolicyNeighbours`: ``idx [Q, k]`` (rows of the data), ``level [Q]``
    (``-1``: fewer than ``k`` within ``max_level``; ``idx == -1``), ``count [Q] = |B_level|``
    and ``overflow [Q]`` (answered by the fallback scan, see the module docstring).
    ``fallback`` (a bool, may be traced): ``False`` skips the scans, overflowing rows get
    ``level == -1`` and ``idx == -1`` (still flagged).  The work is the phases' rounds (one
    each for a usual batch; ``index.phases`` bounds a round) plus one scan of all data per
    overflowing query (none with the measured capacities).
    """
    qcols = _query_columns(index.d_s, index.goal, index.d_g, query_s, query_g)
    q, k = qcols.shape[1], index.k
    seeds = _query_seeds(_key_words(key), jnp.arange(q, dtype=jnp.int32))
    real = jnp.all(jnp.isfinite(qcols), axis=0)
    idx = jnp.full((q, k), -1, jnp.int32)
    level = jnp.full((q,), -1, jnp.int32)
    count = jnp.zeros((q,), jnp.int32)
    over = jnp.zeros((q,), bool)
    if q == 0:
        return PolicyNeighbours(idx=idx, level=level, count=count, overflow=over)
    if not index.grid:  # scan only: every query is a scan (not an overflow)
        res = jax.lax.map(lambda a: _scan_query(index, *a), (seeds, jnp.where(real, qcols, 0.0).T))
        idx, level, count = (jnp.where(real.reshape((-1,) + (1,) * (r.ndim - 1)), r, d)
                             for r, d in zip(res, (idx, level, count)))
        return PolicyNeighbours(idx=idx, level=level, count=count, overflow=over)
    ip, fr = _cells(index, jnp.where(real, qcols, 0.0))
    pending = real
    for phase in index.phases:
        # A round's pool of slots(q) * cap items, shared by up to _SLOT_FACTOR times as many
        # queries (module docstring; phase 0 already takes all q).
        n_pool = phase.slots(q) * phase.cap
        n_slots = min(q, _SLOT_FACTOR * phase.slots(q))

        def round_(state, phase=phase, n_slots=n_slots, n_pool=n_pool):  # the next n_slots queries
            todo, idx, level, count, over = state
            rows = jnp.nonzero(todo, size=n_slots, fill_value=q)[0].astype(jnp.int32)
            sel = jnp.minimum(rows, q - 1)
            slot = rows < q
            r_idx, r_level, r_count, fit, hopeless = _phase(index, seeds[sel], slot, qcols[:, sel], ip[:, sel],
                                                            fr[:, sel], phase, n_slots, n_pool)
            live = jnp.where(slot & fit, rows, q)  # out of range: dropped
            idx = idx.at[live].set(r_idx, mode="drop")
            level = level.at[live].set(r_level, mode="drop")
            count = count.at[live].set(r_count, mode="drop")
            over = over.at[jnp.where(slot & hopeless, rows, q)].set(True, mode="drop")
            todo = todo.at[jnp.where(slot & (fit | hopeless), rows, q)].set(False, mode="drop")
            return todo, idx, level, count, over

        # Rounds until every pending query ran (one round unless the pool or the slots are
        # short: each round finishes at least its smallest stencil).
        _, idx, level, count, over = jax.lax.while_loop(lambda st: jnp.any(st[0]), round_,
                                                        (pending, idx, level, count, over))
        pending = pending & (level < 0) & ~over
    fallback = jnp.asarray(fallback, bool)  # a traced flag: both settings share one compile
    todo = jnp.nonzero(over, size=q, fill_value=0)[0]

    def body(i, res):
        j = todo[i]
        r = _scan_query(index, seeds[j], qcols[:, j])
        return tuple(a.at[j].set(b) for a, b in zip(res, r))

    n_scans = jnp.where(fallback, jnp.sum(over, dtype=jnp.int32), 0)
    # Under a cond: without vmap a step with nothing to scan skips the loop's setup too (the
    # loop-invariant parts XLA hoists out of it and the copies of the index into its state).
    idx, level, count = jax.lax.cond(n_scans > 0,
                                     lambda res: jax.lax.fori_loop(0, n_scans, body, res),
                                     lambda res: res, (idx, level, count))
    lost = over & ~fallback
    idx = jnp.where(lost[:, None], -1, idx)
    level = jnp.where(lost, -1, level)
    return PolicyNeighbours(idx=idx, level=level, count=count, overflow=over)
