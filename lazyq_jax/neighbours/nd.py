"""Exact neighbourhoods ``B(s0, g0)`` (paper §V-A-2) for general state and goal spaces.

Generalises :mod:`lazyq_jax.neighbours.grid` (states ``[N, 2]``, angle goals) to states
``s[N, d_s]`` with ``1 <= d_s <= 10`` and goals that are an angle ``g[N]``, a vector
``g[N, d_g]`` (``1 <= d_g <= 10``) or absent (``None``).

Semantics (the reference the tests check against)
-------------------------------------------------
With ``R2S[L] = float32((radius_s * growth**L)**2)``, ``RG[L] = float32(radius_g * growth**L)``
and ``RG2[L] = float32((radius_g * growth**L)**2)`` (each rounded once from float64, see
:func:`lazyq_jax.neighbours.common.radius_tables`), a data point ``(s, g)`` belongs to
``B_L(s0, g0)`` iff, computed in float32 exactly as written (every product and every
sum rounded to float32, sums left to right)::

    ds2 = ((s[0]-s0[0])**2 + (s[1]-s0[1])**2) + ... + (s[d_s-1]-s0[d_s-1])**2
    ds2 < R2S[L]  and  goal_ok

    angle:  d = |wrap(g) - wrap(g0)|;  min(d, TWO_PI - d) < RG[L]     (as in neighbours.py)
    vector: dg2 = (g[0]-g0[0])**2 + ... + (g[d_g-1]-g0[d_g-1])**2;  dg2 < RG2[L]
    none:   goal_ok = True

``wrap`` and the float32 ``PI``/``TWO_PI`` are those of :mod:`lazyq_jax.neighbours.grid`
(``wrap`` is evaluated on the host in NumPy). ``level`` is the smallest ``L >= 0`` with
``|B_L| >= k``; ``idx`` holds ``k`` distinct indices drawn uniformly without
replacement from ``B_level``; ``count = |B_level|``.

XLA on CPU contracts ``a*b + c`` into a fused multiply-add (measured: about a quarter
of random ``x*x + y*y`` differ in the last bit from the float32 formula), which would
make the jitted test disagree with the definition on pairs within an ulp of a
boundary. Every square here is written ``max(d*d, 0)``: the ``max`` stands between
the product and the sum, so nothing is contracted and the jitted test is bitwise the
formula above (a no-op otherwise: the inputs are checked finite).

Design
------
*Radius units.* Membership is a product of two balls (state: ``radius_s * growth**L``,
goal: ``radius_g * growth**L``). Measured in its own block's radius every axis has the
same radius ``growth**L``, so one grid in radius units serves every level.

*A grid over a few axes chosen from the data, exact filtering on all of them.* The
entries are sorted by the lexicographic cell key of ``m <= 4`` grid axes; a dense table
of cell offsets gives each cell's contiguous range in O(1). The other axes are not
partitioned. A query's level-``L`` stencil is one contiguous range per cell of the
non-last grid axes, the last axis's interval clipped to the chord of the query's ball
(and cells outside the ball in a block dropped): ``R = prod(spans)`` ranges. The first
axis may be *replicated* (as the g-blocks of :mod:`lazyq_jax.neighbours.grid`): every point
is stored ``rep`` times, in the blocks of ``rep`` consecutive cells that contain it, so
one block holds the whole level-0 interval of that axis and ``R`` shrinks by its span
while ranges get longer (fewer partly filled items).
Why a grid and not a tree: under ``jit`` a query is a fixed number of O(1) lookups
with no data-dependent traversal, and one sort serves all levels. Why few axes: a
stencil over ``m`` axes costs ``~3^(m-1)`` ranges while each extra axis prunes less;
in high dimension no axis-aligned partition prunes much (the bound on this design,
see experiments/bench_neighbours_nd.py).
The layout is picked on the host by a cost model: axes ordered by their measured
selectivity (fraction of the data within one radius of sample queries), prefixes of
1-4 axes (the angle, periodic, always first), cell widths 0.25-2 radii (coarsened
until the table has at most ``max(2N, 2^16)`` cells), replication 1 or the first
axis's span; each candidate's exact stencil for ~256 sample queries is measured on a
64k-point subsample (items of ``W`` entries plus a per-range overhead); "no grid" (a
full scan, brute force over all data) is one candidate and is also used by any pass
whose stencil would have more ranges than a full scan has items.
Float safety: data cells are assigned in float64 on the host; each query's cell
position is split on the host into an integer and a fraction, so the stencil
arithmetic under ``jit`` works on small numbers; the stencil is widened by a relative
``1e-5`` of the radius (``+1e-5`` rad for the angle, whose float32 wrap-around is off
by ~1e-6) plus ``1e-4`` cells, far above the float32 error of the test. The grid only
has to cover ``B_L``; membership is always the float32 formula.

*Membership words* (the scheme of :mod:`lazyq_jax.neighbours.grid`). Each range is cut into
items of ``W = 32`` consecutive entries (one contiguous ``[n_cols, 32]`` slice gather
an item, ~3x faster on CPU than gathering lanes); one float32 test per entry and level
gives a 32-bit word per item and level (several levels in one variadic reduction, so
the distances are computed once); per-query counts at every level of a pass are
popcount sums. The closed-form entry level ``ceil(log_growth(...))`` was not needed:
with a word per level the exact test is the only level computation. Sampling draws
``k`` ranks with Floyd's algorithm and maps each to its member through the prefix of
popcounts (a count in a window of the query's prefixes when it has at most 32 items, else
a binary search) and a select-in-word: the shared core of :mod:`lazyq_jax.neighbours.common`.

*Host-driven growth* (as :func:`lazyq_jax.neighbours.grid.search_all`): pass 1 tests level
0 for all queries (sorted by cell key for locality); queries still short of ``k`` are
searched again with levels ``1..3``, ``4..7``, ``8..15``, ... (at most 16 levels a pass,
the stencil of the highest) until the radii cover all data (``|B| = N >= k``).

*Capacities and overflow* (jax-md ``partition.py`` style). Each pass first *measures*
(a cheap jitted pass over the stencils only) the exact number of items of every
pending query, then *allocates*: the cell-sorted queries are packed greedily into
chunks of at most ``limit`` items (about ``chunk_items``) and ``c`` queries (a multiple of
256), both sized so that about as many chunks as either bound alone needs are filled: a
chunk costs its static shapes, not its fill (packing at fixed global boundaries of the
two bounds once made 28 half-full chunks where 16 suffice, 1.5x the pass's time).  ``cap``
(static items a chunk) is the largest chunk's need rounded up to 4 significant bits, so
that few variants compile; the search steps come from the largest per-query count.
Every chunk reports the items it
needed and its largest per-query count; a chunk that did not fit (only possible with
a forced ``item_capacity``, or if the measurement were wrong) is *not* written and is
re-run with the reported need. Nothing is dropped silently. A chunk's inputs are
gathered on the host, so compiled chunks do not depend on the number of queries.

*Devices.* With a ``mesh`` a pass runs its chunks ``D`` at a time (``D`` devices), one
chunk a device, as one ``shard_map`` program (the index replicated; the last group
padded with empty chunks), read back on the host: no collective, one compilation for
the mesh.  Each device computes its chunk by the one-device chunk's operations, so the
result equals the one-device search; checked bitwise on CPU devices
(tests/multidevice_check.py), not by construction (it is another XLA module).  With
several processes each one searches on its own devices of the mesh (no cross-host
traffic; every process gets the whole result).

*Randomness.* Query ``q`` (its row in ``query_s``) draws its bits from a keyed hash of
``(bits(key), q)`` only, so results do not depend on chunking, padding, the pass in
which it finishes or the other queries. Each Floyd draw ``U{0..j}`` is the high word of
a 32x32-bit product with a hashed 32-bit uniform: bias below ``(j + 1) / 2^32``.

Entry points: :func:`find_neighbours_nd` (validate, build, search);
:func:`build_index_nd` then :func:`search_all_nd` to reuse an index.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from jax.sharding import Mesh, PartitionSpec as P

from lazyq_jax.neighbours.common import (TWO_PI, W, Neighbours, _check_params, _draw_ranks, _items, _key_words,
                                         _member_words, _pick_level, _query_seeds, _select_members, _steps,
                                         _without_hugepage_advice, radius_tables, stable_order, wrap_angle)
from lazyq_jax.parallel import AXIS, put, replicated, sharded, to_host

__all__ = ["GridAxis", "NDIndex", "build_index_nd", "find_neighbours_nd", "membership_level_reference",
           "search_all_nd"]

MAX_DIM = 10  # largest d_s and d_g
MAX_GRID_AXES = 4
LEVELS_PER_PASS = 16
MAX_LEVELS = 4096  # growths needed to cover all data; beyond: growth too close to 1
_REL_SLACK = 1e-5  # stencil widening, relative to the radius
_ANGLE_SLACK = 1e-5  # absolute, radians
_CELL_SLACK = 1e-4  # absolute, cells
_CHUNK_ITEMS = 1 << 20  # target items per chunk
_MEASURE_ENTRIES = 1 << 24  # ranges a measuring block (its [B, R] arrays: 64 MB each)
_SAMPLE = 256  # sample queries of the layout cost model
_INT_CLIP = float(1 << 30)
_MAX_REP = 8  # copies of each point when the first grid axis is replicated
_MAX_ENTRIES = 1 << 27  # bound on N * replication


@dataclass(frozen=True)
class GridAxis:
    """One grid axis (static): data column ``col``, cells ``[origin + i*width, origin + (i+1)*width)``."""

    col: int  # column in NDIndex.cols
    block: str  # "s" (state) or "g" (goal)
    periodic: bool  # the angle (period 2pi, origin -pi)
    origin: float
    width: float  # raw units
    n: int  # cells
    radius: float  # block base radius (radius_s or radius_g)
    rep: int = 1  # > 1: replicated (first axis only): block b holds cells b .. b + rep - 1

    @property
    def n_key(self) -> int:
        """Cells (or blocks, if replicated) of this axis in the sort key."""
        return self.n if self.rep == 1 or self.periodic else self.n + self.rep - 1

    def rho_cells(self, level: int, growth: float) -> float:
        """Half-width of the level-``level`` ball along this axis in cells, widened (see module doc)."""
        r = self.radius * growth**level * (1 + _REL_SLACK) + (_ANGLE_SLACK if self.periodic else 0.0)
        return r / self.width + _CELL_SLACK

    def span(self, level: int, growth: float) -> int:
        """Static number of cells the stencil can touch on this axis."""
        rc = self.rho_cells(level, growth)
        return self.n if 2 * rc + 2 >= self.n else math.floor(2 * rc + 0.01) + 2

    def enum(self, level: int, growth: float) -> tuple[int, bool]:
        """``(ranges enumerated on this axis, whole axis)`` of the level-``level`` stencil."""
        span = self.span(level, growth)
        if self.rep == 1:
            return span, span >= self.n
        nb = -(-span // self.rep)
        if span >= self.n or (self.periodic and nb * self.rep > self.n):
            return -(-self.n // self.rep), True  # blocks 0, rep, 2 rep, ...: every cell once
        return nb, False


@struct.dataclass
class NDIndex:
    """Data sorted by grid cell (see module docstring); build with :func:`build_index_nd`."""

    cols: jax.Array  # float32 [n_cols, E + W]: state dims, then the wrapped angle or the goal dims
    orig: jax.Array  # int32 [E]: original index of each sorted entry (E = N * replication)
    offsets: jax.Array  # int32 [n_cells + 1]: first entry of each cell
    k: int = struct.field(pytree_node=False)
    radius_s: float = struct.field(pytree_node=False)
    radius_g: float = struct.field(pytree_node=False)
    growth: float = struct.field(pytree_node=False)
    d_s: int = struct.field(pytree_node=False)
    goal: str = struct.field(pytree_node=False)  # "angle" | "vector" | "none"
    d_g: int = struct.field(pytree_node=False)  # 1 for angle, 0 for none
    grid: tuple = struct.field(pytree_node=False)  # tuple[GridAxis], slowest first; () = full scan
    col_lo: tuple = struct.field(pytree_node=False)  # per column data min (host floats)
    col_hi: tuple = struct.field(pytree_node=False)
    n_points: int = struct.field(pytree_node=False)  # N

    @property
    def n_entries(self) -> int:
        return int(self.orig.shape[0])


# ----------------------------------------------------------------------------- validation


def _points(s, g, what):
    """Validate one point set; returns ``(cols float32 [n_cols, n], d_s, goal kind, d_g)``."""
    s = np.asarray(s)
    if s.ndim != 2 or not 1 <= s.shape[1] <= MAX_DIM:
        raise ValueError(f"{what}_s must have shape [n, d_s] with 1 <= d_s <= {MAX_DIM}, got {s.shape}")
    n, d_s = s.shape
    s = s.astype(np.float32)
    if g is None:
        kind, d_g, gcols = "none", 0, np.zeros((0, n), np.float32)
    else:
        g = np.asarray(g)
        if g.shape == (n,):
            kind, d_g = "angle", 1
        elif g.ndim == 2 and g.shape[0] == n and 1 <= g.shape[1] <= MAX_DIM:
            kind, d_g = "vector", g.shape[1]
        else:
            raise ValueError(f"{what}_g must be None, an angle [{n}] or a vector [{n}, d_g] with "
                             f"1 <= d_g <= {MAX_DIM} to match {what}_s {s.shape}, got {g.shape}")
        g = g.astype(np.float32)
        if not np.isfinite(g).all():
            raise ValueError(f"{what}_g contains NaN or inf; remove or fix those points")
        gcols = wrap_angle(g)[None, :] if kind == "angle" else g.T
    if not np.isfinite(s).all():
        raise ValueError(f"{what}_s contains NaN or inf; remove or fix those points")
    cols = np.ascontiguousarray(np.concatenate([s.T, gcols], axis=0), dtype=np.float32)
    return cols, d_s, kind, d_g


def _check_match(index: NDIndex, d_s, kind, d_g):
    if d_s != index.d_s:
        raise ValueError(f"query_s has d_s={d_s} but the data have d_s={index.d_s}")
    if kind != index.goal:
        raise ValueError(f"query goals are {kind!r} but the data goals are {index.goal!r} "
                         "(None: no goal; [n]: angle; [n, d_g]: vector)")
    if d_g != index.d_g:
        raise ValueError(f"query_g has d_g={d_g} but the data goals have d_g={index.d_g}")


# ----------------------------------------------------------------------------- reference


def membership_level_reference(data_s, data_g, query_s, query_g, *, radius_s=0.06, radius_g=0.1,
                               growth=2 ** (1 / 3), max_level=400):
    """NumPy float32 reference: ``lam [Q, N]``, the smallest ``L`` with the point in ``B_L``.

    ``level = k-th smallest lam`` per row and ``count = (lam <= level).sum()``. Memory
    ``O(Q N)``: for tests and benchmark checks.
    """
    dc, d_s, kind, d_g = _points(data_s, data_g, "data")
    qc, *_ = _points(query_s, query_g, "query")
    lv = np.arange(max_level + 1)
    with np.errstate(over="ignore"):  # radii beyond float32: inf, a fine threshold
        r2s, rg = radius_tables(radius_s, radius_g, growth, lv)
        rg2, _ = radius_tables(radius_g, radius_g, growth, lv)
    ds2 = None
    for c in range(d_s):
        v = dc[c][None, :] - qc[c][:, None]
        ds2 = v * v if ds2 is None else ds2 + v * v
    lam = np.searchsorted(r2s, ds2.ravel(), side="right").reshape(ds2.shape)
    if kind == "angle":
        d = np.abs(dc[d_s][None, :] - qc[d_s][:, None])
        dg = np.minimum(d, TWO_PI - d)
        lam = np.maximum(lam, np.searchsorted(rg, dg.ravel(), side="right").reshape(dg.shape))
    elif kind == "vector":
        dg2 = None
        for c in range(d_s, d_s + d_g):
            v = dc[c][None, :] - qc[c][:, None]
            dg2 = v * v if dg2 is None else dg2 + v * v
        lam = np.maximum(lam, np.searchsorted(rg2, dg2.ravel(), side="right").reshape(dg2.shape))
    return lam


# ----------------------------------------------------------------------------- grid (host + jit)


def _cell_coords(ax: GridAxis, x):
    """Position in cells (float64, host): ``(x - origin) / width``."""
    return (np.asarray(x, np.float64) - ax.origin) / ax.width


def _data_cells(grid, cols):
    """``(block, rest)``: int64 ``[N, rep]`` key of the first axis (one column a copy) and
    ``[N]`` key of the other axes; the sort key is ``block * prod(n of the others) + rest``."""
    n = cols.shape[1]
    if not grid:
        return np.zeros((n, 1), np.int64), np.zeros(n, np.int64)
    rest = np.zeros(n, np.int64)
    for ax in grid[1:]:
        rest = rest * ax.n + np.clip(np.floor(_cell_coords(ax, cols[ax.col])), 0, ax.n - 1).astype(np.int64)
    ax = grid[0]
    c0 = np.clip(np.floor(_cell_coords(ax, cols[ax.col])), 0, ax.n - 1).astype(np.int64)
    block = c0[:, None] - np.arange(ax.rep)[None, :]  # the blocks that contain the point's cell
    block = np.mod(block, ax.n) if ax.periodic else block + (ax.rep - 1)
    return block, rest


def _table(grid, cols):
    """Unsorted entries of the table: ``(key [E], src [E])``."""
    block, rest = _data_cells(grid, cols)
    stride = math.prod(ax.n for ax in grid[1:])
    return (block * stride + rest[:, None]).ravel(), np.repeat(np.arange(cols.shape[1]), block.shape[1])


def _query_cells(grid, cols):
    """``(ip int32 [m, Q], fr float32 [m, Q], key int64 [Q])``: integer and fractional cell position."""
    m, q = len(grid), cols.shape[1]
    ip = np.zeros((m, q), np.int32)
    fr = np.zeros((m, q), np.float32)
    key = np.zeros(q, np.int64)
    for j, ax in enumerate(grid):
        u = _cell_coords(ax, cols[ax.col])
        f = np.floor(u)
        ip[j] = np.clip(f, -(1 << 29), 1 << 29).astype(np.int32)
        fr[j] = np.clip(u - f, 0.0, np.nextafter(np.float32(1), np.float32(0)))
        key = key * ax.n + np.clip(ip[j], 0, ax.n - 1)
    return ip, fr, key


def _n_ranges(grid, level, growth) -> int:
    return int(np.prod([ax.enum(level, growth)[0] for ax in grid[:-1]], dtype=np.int64)) if grid else 1


def _use_full_scan(grid, level, growth, n_entries) -> bool:
    """A full scan (``N/W`` items) is cheaper than a stencil with that many ranges."""
    return not grid or _n_ranges(grid, level, growth) * 4 * W > max(n_entries, 4 * W)


def _full_ranges(xp, grid, offsets, s):
    """Every data point once: all entries, or (replicated first axis) one range per block of a
    partition of its cells."""
    i32 = jnp.int32 if xp is jnp else np.int64
    if not grid or grid[0].rep == 1:
        return xp.zeros((s, 1), i32), xp.full((s, 1), offsets[-1], i32)
    ax = grid[0]
    stride = math.prod(a.n for a in grid[1:])
    blocks = np.arange(0, ax.n, ax.rep) + (0 if ax.periodic else ax.rep - 1)
    start = offsets[blocks * stride]
    end = offsets[(blocks + 1) * stride]
    shape = (s, blocks.size)
    return xp.broadcast_to(start[None, :], shape), xp.broadcast_to((end - start)[None, :], shape)


def _ranges(xp, grid, offsets, ip, fr, level: int, growth: float, full: bool = False):
    """Stencil of ``B_level`` as ranges of sorted entries: ``(start, length, span_bad)``, ``[S, R]``.

    ``xp`` is ``numpy`` (host estimates, float64) or ``jax.numpy`` (under jit, float32).
    ``span_bad`` flags a query whose cell interval exceeded the static span (never
    expected; reported as an overflow rather than truncated).
    """
    f = jnp.float32 if xp is jnp else np.float64
    i32 = jnp.int32 if xp is jnp else np.int64
    s = ip.shape[1]
    if full:
        start, length = _full_ranges(xp, grid, offsets, s)
        return start, length, xp.zeros((s,), bool)
    fr = fr.astype(f)
    last = grid[-1]
    spans = [ax.enum(level, growth)[0] for ax in grid[:-1]]
    r_total = int(np.prod(spans, dtype=np.int64)) if spans else 1
    r = xp.arange(r_total)
    valid = xp.ones((s, r_total), bool)
    span_bad = xp.zeros((s,), bool)
    prefix = xp.zeros((s, r_total), i32)
    block_sum = {"s": xp.zeros((s, r_total), f), "g": xp.zeros((s, r_total), f)}
    stride = r_total
    for j, ax in enumerate(grid[:-1]):
        span = spans[j]
        stride //= span
        t = ((r // stride) % span).astype(i32)[None, :]
        rc = ax.rho_cells(level, growth)
        if ax.enum(level, growth)[1]:
            lo = xp.zeros((s,), i32)
            cnt = xp.full((s,), ax.n, i32)
        else:
            a = xp.clip(xp.floor(fr[j] - f(rc)), -_INT_CLIP, _INT_CLIP).astype(i32)
            b = xp.clip(xp.floor(fr[j] + f(rc)), -_INT_CLIP, _INT_CLIP).astype(i32)
            lo, hi = ip[j].astype(i32) + a, ip[j].astype(i32) + b
            if ax.periodic:
                cnt = xp.minimum(hi - lo + 1, ax.n)
                lo = xp.mod(lo, ax.n)
            else:
                lo, hi = xp.clip(lo, 0, ax.n - 1), xp.clip(hi, 0, ax.n - 1)
                cnt = hi - lo + 1
            span_bad = span_bad | (cnt > ax.span(level, growth))
        # t-th cell (or block of ax.rep cells) of the interval; t beyond it: invalid.
        cell = lo[:, None] + t * ax.rep
        valid = valid & (t * ax.rep < cnt[:, None])
        if ax.periodic:
            cell = xp.mod(cell, ax.n)
            key = cell
        else:
            cell = xp.minimum(cell, ax.n - 1)
            key = cell + (ax.rep - 1)
        prefix = prefix * ax.n_key + key
        if not ax.periodic:  # distance from the query to the cells, raw units, for the ball test
            rel = (cell - ip[j].astype(i32)[:, None]).astype(f)
            frj = fr[j][:, None]
            dmin = xp.maximum(xp.maximum(rel - frj, frj - rel - ax.rep), 0) * f(ax.width)
            block_sum[ax.block] = block_sum[ax.block] + dmin * dmin
    rho_raw = {ax.block: f(ax.radius * growth**level * (1 + _REL_SLACK)) for ax in grid}  # block radii
    for b in ("s", "g"):
        if any(ax.block == b and not ax.periodic for ax in grid[:-1]):
            valid = valid & (block_sum[b] < rho_raw[b] * rho_raw[b])
    if any(ax.block == last.block for ax in grid[:-1]):
        hw = xp.sqrt(xp.maximum(rho_raw[last.block] ** 2 - block_sum[last.block], 0)) / f(last.width)
        hw = hw + f(_CELL_SLACK)
    else:
        hw = xp.full((s, r_total), f(last.rho_cells(level, growth)), f)
    frl = fr[-1][:, None]
    ipl = ip[-1].astype(i32)[:, None]
    a = xp.clip(xp.floor(frl - hw), -_INT_CLIP, _INT_CLIP).astype(i32)
    b = xp.clip(xp.floor(frl + hw), -_INT_CLIP, _INT_CLIP).astype(i32)
    lo_l = xp.clip(ipl + a, 0, last.n - 1)
    hi_l = xp.clip(ipl + b, 0, last.n - 1)
    base = prefix * last.n
    start = offsets[base + lo_l]
    end = offsets[base + hi_l + 1]
    length = xp.where(valid, end - start, 0)
    return start, length, span_bad


# ----------------------------------------------------------------------------- grid choice (host)


def _axes_info(d_s, kind, d_g, radius_s, radius_g):
    info = [(c, "s", False, radius_s) for c in range(d_s)]
    if kind == "angle":
        info.append((d_s, "g", True, radius_g))
    elif kind == "vector":
        info += [(d_s + c, "g", False, radius_g) for c in range(d_g)]
    return info


def _make_grid(axes, widths, col_lo, col_hi, rep=1):
    grid = []
    for j, ((col, block, periodic, radius), h) in enumerate(zip(axes, widths)):
        r = rep if j == 0 else 1
        if periodic:  # a replicated periodic axis has a multiple of rep cells (see _ranges)
            n = r * max(1, math.floor(2 * math.pi / (h * radius * r)))
            grid.append(GridAxis(col, block, True, -math.pi, 2 * math.pi / n, n, radius, r))
        else:
            w = h * radius
            n = math.floor((col_hi[col] - col_lo[col]) / w) + 1
            grid.append(GridAxis(col, block, False, col_lo[col], w, n, radius, r))
    return tuple(grid)


def _table_limit(n):
    return max(2 * n, 1 << 16)


def _coarsen(axes, widths, col_lo, col_hi, n, rep=1):
    """Double the cell widths until the offset table fits (sparse, wide data)."""
    for _ in range(80):
        grid = _make_grid(axes, widths, col_lo, col_hi, rep)
        if math.prod(ax.n_key for ax in grid) <= _table_limit(n):
            return grid
        widths = [2 * h for h in widths]
    return None


def _offsets(grid, key):
    n_cells = math.prod(ax.n_key for ax in grid)
    offsets = np.zeros(n_cells + 1, np.int64)
    np.cumsum(np.bincount(key, minlength=n_cells), out=offsets[1:])
    return offsets


def _grid_cost(grid, cols_sub, n_data, qcols, growth):
    """Estimated work per query (items of W lanes + ranges) at level 0, from a data subsample."""
    rep = grid[0].rep if grid else 1
    if _use_full_scan(grid, 0, growth, n_data * rep):
        return n_data / W + _n_ranges(grid, 0, growth) * 0.25
    n_sub = cols_sub.shape[1]
    offsets = _offsets(grid, _table(grid, cols_sub)[0])
    ip, fr, _ = _query_cells(grid, qcols)
    _, length, _ = _ranges(np, grid, offsets, ip.astype(np.int64), fr, 0, growth)
    est = length * (n_data / n_sub)
    per_range = np.ceil(est / W) + 0.25  # items (the last one of a range partly empty) + plan
    return float(per_range.sum(axis=1).mean())


def _choose_grid(cols, d_s, kind, d_g, radius_s, radius_g, growth, qcols, col_lo, col_hi):
    """Cheapest grid by :func:`_grid_cost` over axis prefixes (by selectivity), cell widths and
    replication of the first axis."""
    n = cols.shape[1]
    rng = np.random.default_rng(0)  # affects speed only, never results
    sub = cols[:, rng.choice(n, min(n, 1 << 16), replace=False)] if n > (1 << 16) else cols
    qs = qcols[:, rng.choice(qcols.shape[1], min(qcols.shape[1], _SAMPLE), replace=False)]
    info = _axes_info(d_s, kind, d_g, radius_s, radius_g)
    # Selectivity: fraction of the data within one base radius of a query along the axis.
    sel = []
    for col, _block, periodic, radius in info:
        x = np.sort(sub[col].astype(np.float64))
        q = qs[col].astype(np.float64)
        if periodic:
            x = np.concatenate([x - 2 * np.pi, x, x + 2 * np.pi])
        frac = (np.searchsorted(x, q + radius) - np.searchsorted(x, q - radius)) / sub.shape[1]
        sel.append(float(frac.mean()))
    order = [info[i] for i in np.argsort(sel, kind="stable")]
    max_rep = max(1, min(_MAX_REP, _MAX_ENTRIES // max(n, 1)))
    best, best_cost = (), n / W * 1.0
    for m in range(1, min(MAX_GRID_AXES, len(order)) + 1):
        axes = order[:m]
        axes = [a for a in axes if a[2]] + [a for a in axes if not a[2]]  # periodic first
        if axes[-1][2]:
            continue  # the contiguous (last) axis must not be periodic
        for h_other in (0.5, 1.0, 2.0):
            for h_last in (0.25, 0.5, 1.0):
                if h_last > h_other or (m == 1 and h_other != 1.0):
                    continue
                widths = [h_other] * (m - 1) + [h_last]
                plain = _coarsen(axes, widths, col_lo, col_hi, n)
                if plain is None:
                    continue
                span0 = plain[0].span(0, growth)
                reps = [1] + ([r for r in {span0, span0 - 1} if 2 <= r <= max_rep and 2 * r <= plain[0].n]
                              if m >= 2 else [])
                for r in sorted(reps):
                    grid = plain if r == 1 else _coarsen(axes, widths, col_lo, col_hi, n, r)
                    if grid is None:
                        continue
                    cost = _grid_cost(grid, sub, n, qs, growth) * (1 + 0.02 * (r - 1))  # + memory
                    if cost < best_cost * 0.98:
                        best, best_cost = grid, cost
    return best


def _sorted_table(grid, cols):
    """``(src [E], offsets)``: entries sorted by key (the copies by a radix sort on block ids)."""
    block, rest = _data_cells(grid, cols)
    stride = math.prod(ax.n for ax in grid[1:])
    offsets = _offsets(grid, (block * stride + rest[:, None]).ravel())
    by_rest = stable_order(rest)
    if block.shape[1] == 1:
        return by_rest[stable_order(block[by_rest, 0])], offsets
    blocks = block[by_rest].ravel()  # copies of each point adjacent, points in rest order
    order = stable_order(blocks)
    return by_rest[order // block.shape[1]], offsets


def _sorted_columns(grid, cols):
    """``(src, offsets, sorted_cols)``: the entries sorted by :func:`_sorted_table` (all points
    in order for the empty grid, a scan) and their columns ``[n_cols, E + W]`` (``W`` zero
    entries at the end: every item one contiguous slice), NumPy's huge-page advice off while
    they are allocated (:func:`lazyq_jax.neighbours.common._without_hugepage_advice`)."""
    n = cols.shape[1]
    with _without_hugepage_advice():
        if grid:
            src, offsets = _sorted_table(grid, cols)
        else:
            src, offsets = np.arange(n), np.array([0, n], np.int64)
        sorted_cols = np.zeros((cols.shape[0], src.size + W), np.float32)
        for c in range(cols.shape[0]):
            np.take(cols[c], src, out=sorted_cols[c, :src.size])
    return src, offsets, sorted_cols


# ----------------------------------------------------------------------------- index


def build_index_nd(data_s, data_g=None, *, k=20, radius_s=0.06, radius_g=0.1, growth=2 ** (1 / 3),
                   query_sample=None, grid=None) -> NDIndex:
    """Sort the data into the grid chosen for them (host, NumPy).

    ``query_sample``: ``(query_s, query_g)`` whose distribution the grid is tuned for
    (default: the data). ``grid``: force a layout, a sequence of ``(axis, width_in_radii)``
    (the first may be ``(axis, width, replication)``) with axis ``0..d_s-1`` a state dim and
    ``d_s..`` the goal dims (the angle is axis ``d_s``; the last axis must not be the angle);
    ``()`` forces a full scan. Used by tests; the default chooses by measured cost.
    """
    _check_params(k, radius_s, radius_g, growth)
    cols, d_s, kind, d_g = _points(data_s, data_g, "data")
    n = cols.shape[1]
    if n < k:
        raise ValueError(f"need at least k={k} data points to draw k distinct neighbours, got {n}")
    col_lo = tuple(float(v) for v in cols.min(axis=1))
    col_hi = tuple(float(v) for v in cols.max(axis=1))
    if grid is None:
        if query_sample is not None:
            qcols, qd_s, qkind, qd_g = _points(*query_sample, "query")
            if (qd_s, qkind, qd_g) != (d_s, kind, d_g) or qcols.shape[1] == 0:
                qcols = cols
        else:
            qcols = cols
        chosen = _choose_grid(cols, d_s, kind, d_g, radius_s, radius_g, growth, qcols, col_lo, col_hi)
    else:
        info = _axes_info(d_s, kind, d_g, radius_s, radius_g)
        spec = [tuple(a) for a in grid]
        rep = int(spec[0][2]) if spec and len(spec[0]) == 3 else 1
        bad = (len(spec) > MAX_GRID_AXES or any(len(a) != 2 for a in spec[1:])
               or any(len(a) not in (2, 3) for a in spec) or any(not 0 <= a[0] < len(info) for a in spec)
               or len({a[0] for a in spec}) != len(spec) or any(not (a[1] > 0) for a in spec)
               or not 1 <= rep <= _MAX_REP or (rep > 1 and len(spec) < 2))
        if bad:
            raise ValueError(f"grid must list at most {MAX_GRID_AXES} distinct axes in [0, {len(info)}) "
                             f"as (axis, width) with positive widths (the first may add a replication "
                             f"1..{_MAX_REP}, with at least 2 axes), got {grid!r}")
        if spec and info[spec[-1][0]][2]:
            raise ValueError("the last grid axis must not be the (periodic) angle")
        chosen = (_coarsen([info[a[0]] for a in spec], [a[1] for a in spec], col_lo, col_hi, n, rep)
                  if spec else ())
    src, offsets, sorted_cols = _sorted_columns(chosen, cols)
    return NDIndex(cols=jnp.asarray(sorted_cols), orig=jnp.asarray(src.astype(np.int32)),
                   offsets=jnp.asarray(offsets.astype(np.int32)), k=int(k), radius_s=float(radius_s),
                   radius_g=float(radius_g), growth=float(growth), d_s=d_s, goal=kind, d_g=d_g,
                   grid=tuple(chosen), col_lo=col_lo, col_hi=col_hi, n_points=n)


# ----------------------------------------------------------------------------- jitted core


def _search_chunk(index: NDIndex, seed, real, qcols, ip, fr, *, lo, hi, cap, full):
    """Levels ``lo..hi`` for one chunk of queries (stencil of level ``hi``) and each query's
    ``k`` ranks: the first of a chunk's two programs (:func:`_select_chunk` is the second;
    :func:`lazyq_jax.neighbours.common._draw_ranks` says why two).

    Returns ``(sample, level, count, need, max_items, span_bad)``; the results are valid only
    if ``need <= cap``, ``max_items < 2**steps`` and not ``span_bad`` (checked by the caller).
    ``level == -1`` where ``|B_hi| < k``.
    """
    k = index.k
    c = qcols.shape[1]
    start, length, bad = _ranges(jnp, index.grid, index.offsets, ip, fr, hi, index.growth, full)
    span_bad = (bad & real).any()
    length = jnp.where(real[:, None], length, 0)  # padding rows cost nothing
    nit = (length + W - 1) // W
    need = jnp.sum(nit.astype(jnp.float32))  # float: immune to int32 wrap-around
    max_items = jnp.max(jnp.sum(nit.astype(jnp.float32), axis=1))
    item_q, item_start, item_valid, first, n_q = _items(start, length, cap)
    words = _member_words(index, qcols, item_q, item_start, item_valid, lo, hi)
    found, li, level, m = _pick_level(words, item_q, c, k, lo)
    word, prefix, ranks = _draw_ranks(words, li, found, m, seed, item_q, k=k)
    sample = (word, prefix, ranks, found, item_start, first, n_q)
    return sample, level.astype(jnp.int32), m.astype(jnp.int32), need, max_items, span_bad


@partial(jax.jit, static_argnames=("lo", "hi", "cap", "full"))
def _chunk(index: NDIndex, key_words, rows, qcols, ip, fr, *, lo, hi, cap, full):
    """:func:`_search_chunk` on one chunk of ``C`` queries (their rows in ``query_s``, ``-1`` =
    padding, and their columns/cells gathered on the host, so that the compiled chunk does
    not depend on the number of queries)."""
    return _search_chunk(index, _query_seeds(key_words, rows), rows >= 0, qcols, ip, fr,
                         lo=lo, hi=hi, cap=cap, full=full)


@partial(jax.jit, static_argnames=("steps",))
def _select_chunk(orig, sample, *, steps):
    """A chunk's second program: each rank of :func:`_chunk`'s ``sample`` mapped to its member
    (``steps``: at least the bit length of the most items of a query)."""
    return _select_members(orig, *sample, steps=steps)


@partial(jax.jit, static_argnames=("lo", "hi", "cap", "full", "mesh"))
def _chunks_on_mesh(index: NDIndex, key_words, rows, qcols, ip, fr, *, lo, hi, cap, full, mesh):
    """``mesh.size`` chunks (inputs stacked on a leading axis), one a device: each device runs
    :func:`_chunk`'s program on its chunk; the results stacked likewise."""
    def one(index, key_words, rows, qcols, ip, fr):  # one device: its chunk, through _chunk
        res = _chunk(index, key_words, rows[0], qcols[0], ip[0], fr[0], lo=lo, hi=hi, cap=cap, full=full)
        return jax.tree.map(lambda r: r[None], res)

    return jax.shard_map(one, mesh=mesh, in_specs=(P(), P(), *[P(AXIS)] * 4), out_specs=P(AXIS),
                         check_vma=False)(index, key_words, rows, qcols, ip, fr)


@partial(jax.jit, static_argnames=("steps", "mesh"))
def _select_on_mesh(orig, sample, *, steps, mesh):
    """:func:`_select_chunk` on each device's chunk of :func:`_chunks_on_mesh`'s samples."""
    def one(orig, sample):
        return _select_chunk(orig, jax.tree.map(lambda r: r[0], sample), steps=steps)[None]

    return jax.shard_map(one, mesh=mesh, in_specs=(P(), P(AXIS)), out_specs=P(AXIS),
                         check_vma=False)(orig, sample)


@partial(jax.jit, static_argnames=("level", "full"))
def _count_items(index: NDIndex, ip, fr, real, *, level, full):
    """Exact items per query (int32 ``[B]``) of the level-``level`` stencil; padding rows 0.

    ``ip``/``fr``: ``[m, B]``, ``real``: bool ``[B]``.  One block a call: the host loops over
    blocks (a ``lax.map`` over blocks ran 2.5-3x slower on the CPU than the same blocks as
    separate calls).
    """
    _, length, _ = _ranges(jnp, index.grid, index.offsets, ip, fr, level, index.growth, full)
    return jnp.where(real, ((length + W - 1) // W).sum(axis=1), 0)


def _pow2(n: int) -> int:
    return 1 << max(int(n) - 1, 0).bit_length()


def _bucket(n: int) -> int:
    """Round up to 4 significant bits (bounds recompiles, < 13% waste)."""
    n = max(int(n), 1)
    unit = 1 << max(n.bit_length() - 4, 0)
    return -(-n // unit) * unit


def _pack(n_it, limit: int, c: int):
    """Starts of greedy chunks over queries in order: each chunk takes queries while it holds
    at most ``limit`` items (at least one query) and ``c`` queries.  One ``searchsorted`` a
    chunk."""
    cum = np.concatenate([[0], np.cumsum(n_it, dtype=np.int64)])
    starts, p, n = [], 0, n_it.size
    while p < n:
        starts.append(p)
        end = int(np.searchsorted(cum, cum[p] + limit, side="right")) - 1  # cum[end] - cum[p] <= limit
        p = max(min(end, p + c, n), p + 1)
    return np.asarray(starts, np.int64)


def _local_mesh(mesh: Mesh | None) -> Mesh | None:
    """The devices the chunks run on: ``None`` for no mesh or one device (the one-device
    path), else the mesh's devices of this process (with several processes each searches
    on its own devices: every process needs the whole result on its host, and the chunks
    cross no process boundary)."""
    if mesh is None or mesh.size == 1:
        return None
    if jax.process_count() == 1:
        return mesh
    local = [d for d in mesh.devices.flat if d.process_index == jax.process_index()]
    return None if len(local) <= 1 else Mesh(np.array(local), (AXIS,))


def _levels_to_cover(index: NDIndex, qcols) -> int:
    """A level whose radii cover every (data, query) pair (so ``|B| = N >= k`` there)."""
    lo = np.minimum(np.asarray(index.col_lo), qcols.min(axis=1))
    hi = np.maximum(np.asarray(index.col_hi), qcols.max(axis=1))
    span = hi.astype(np.float64) - lo.astype(np.float64)
    diag_s = float(np.sqrt(np.sum(span[:index.d_s] ** 2)))
    diag_g = {"angle": math.pi, "none": 0.0}.get(index.goal, float(np.sqrt(np.sum(span[index.d_s:] ** 2))))
    lg = math.log(index.growth)
    need = [math.ceil(math.log(d / r) / lg) for d, r in ((diag_s, index.radius_s), (diag_g, index.radius_g))
            if d > 0]
    return 1 + max([0] + need)


def search_all_nd(index: NDIndex, key, query_s, query_g=None, *, n_queries: int | None = None,
                  item_capacity: int | None = None, chunk_items: int = _CHUNK_ITEMS,
                  stats: dict | None = None, mesh: Mesh | None = None) -> Neighbours:
    """Exact neighbours of any number of queries (host-driven passes; not jittable).

    ``n_queries``: only the first rows are searched, the rest are padding (results 0).
    ``item_capacity``: force the first item capacity of every chunk (tests: a small value
    makes chunks overflow, which is detected and re-run with the measured need).
    ``chunk_items``: target items per chunk. ``stats``: if a dict, filled with per-pass
    information (``passes``: list of dicts; ``overflow_chunks``: chunks re-run).
    ``mesh``: the chunks run on its devices (module docstring, *Devices*); a one-device
    mesh is the one-device path.
    """
    qcols, d_s, kind, d_g = _points(query_s, query_g, "query")
    _check_match(index, d_s, kind, d_g)
    n_q = qcols.shape[1]
    n_real = n_q if n_queries is None else int(n_queries)
    if not 0 <= n_real <= n_q:
        raise ValueError(f"n_queries={n_queries} must lie in [0, {n_q}]")
    if item_capacity is not None and int(item_capacity) < 1:
        raise ValueError(f"item_capacity must be a positive int, got {item_capacity!r}")
    if int(chunk_items) < 1:
        raise ValueError(f"chunk_items must be a positive int, got {chunk_items!r}")
    chunk_items = int(chunk_items)
    k = index.k
    if stats is not None:
        stats.update(passes=[], overflow_chunks=0, grid=index.grid)
    if n_q == 0:
        z = jnp.zeros((0,), jnp.int32)
        return Neighbours(idx=jnp.zeros((0, k), jnp.int32), level=z, count=z)
    level_all = _levels_to_cover(index, qcols[:, :max(n_real, 1)])
    if level_all > MAX_LEVELS:
        raise ValueError(f"growth={index.growth} is too close to 1: covering the data takes {level_all} "
                         f"growths (more than {MAX_LEVELS})")
    ip, fr, qkey = _query_cells(index.grid, qcols)
    order = stable_order(qkey[:n_real])
    out_idx = np.zeros((n_q, k), np.int32)
    out_level = np.zeros(n_q, np.int32)
    out_count = np.zeros(n_q, np.int32)
    key_words = _key_words(key)
    mesh = _local_mesh(mesh)
    # the chunks' copies on the mesh (the measuring pass stays on the default device)
    on_mesh = None if mesh is None else put((index, key_words), replicated(mesh))

    def chunk_inputs(ci):
        """Host-side inputs of chunk ``ci`` (``-1``: padding, ``ci = None``: an empty chunk):
        slices of this pass's gathered queries, padded to ``c``."""
        rows = np.full(c, -1, np.int64)
        out = [np.zeros((a.shape[0], c), a.dtype) for a in pass_inputs]
        if ci is not None:
            a, b = chunk_start[ci], chunk_start[ci + 1]
            rows[:b - a] = pending[a:b]
            for o, x in zip(out, pass_inputs):
                o[:, :b - a] = x[:, a:b]
        return (rows, *out)

    def run_chunks(ids, steps, **static):
        """Chunks ``ids``, dispatched asynchronously: ``[(ci, results)]``."""
        if mesh is None:
            done = []
            for ci in ids:
                sample, *rest = _chunk(index, key_words, *map(jnp.asarray, chunk_inputs(ci)), **static)
                done.append((ci, (_select_chunk(index.orig, sample, steps=steps), *rest)))
            return done
        d, groups = mesh.size, []
        for g0 in range(0, len(ids), d):  # D chunks a program, the last group padded (rows -1)
            group = ids[g0:g0 + d]
            inputs = [np.stack(x) for x in zip(*map(chunk_inputs, group + [None] * (d - len(group))))]
            sample, *rest = _chunks_on_mesh(*on_mesh, *put(inputs, sharded(mesh)), mesh=mesh, **static)
            groups.append((group, (_select_on_mesh(on_mesh[0].orig, sample, steps=steps, mesh=mesh), *rest)))
        # read on the host: indexing the sharded results on the devices would be a program
        # with collectives
        done = []
        for group, res in groups:
            res = to_host(res)
            done += [(ci, tuple(r[j] for r in res)) for j, ci in enumerate(group)]
        return done

    pending, lo, hi = order, 0, 0
    while pending.size:
        t_pass = time.perf_counter()
        full = _use_full_scan(index.grid, hi, index.growth, index.n_entries)
        # This pass's queries, gathered once (pending is in cell order): the measuring blocks
        # and the chunks are slices of them.
        pass_inputs = (qcols[:, pending], ip[:, pending], fr[:, pending])
        # Measure: exact items of every pending query at this pass's stencil.
        if full and (not index.grid or index.grid[0].rep == 1):
            n_it = np.full(pending.size, -(-index.n_entries // W), np.int64)
        else:
            r_max = max(_n_ranges(index.grid, hi, index.growth), 1)  # ranges a query (bounds the full scan's)
            blk = max(min(_pow2(pending.size), _pow2(_MEASURE_ENTRIES // r_max + 1) // 2), 256)
            counts = []
            for b0 in range(0, pending.size, blk):
                n_b = min(blk, pending.size - b0)
                ip_b, fr_b = (np.pad(x[:, b0:b0 + n_b], ((0, 0), (0, blk - n_b))) for x in pass_inputs[1:])
                counts.append(_count_items(index, jnp.asarray(ip_b), jnp.asarray(fr_b),
                                           jnp.asarray(np.arange(blk) < n_b), level=hi, full=full))
            n_it = np.concatenate([np.asarray(x) for x in counts])[:pending.size].astype(np.int64)
        # Allocate: pack the (cell-sorted) queries greedily into chunks of at most ``limit``
        # items and ``c`` queries, sized for about as many chunks as either bound alone needs
        # (few distinct compiled chunks; the static shapes are what a chunk costs).
        max_n, total = int(n_it.max()), int(n_it.sum())
        n_chunks = max(-(-total // chunk_items), -(-pending.size // (1 << 16)), 1)
        limit = max(_bucket(-(-total // n_chunks)), max_n)
        c = -(-(pending.size * 9 // 8 // n_chunks + 1) // 256) * 256
        chunk_start = np.append(_pack(n_it, limit, c), pending.size)
        n_chunks = chunk_start.size - 1
        cap = _bucket(np.add.reduceat(n_it, chunk_start[:-1]).max())
        if item_capacity is not None:
            cap = int(item_capacity)
        steps = _steps(max_n)
        info = {"lo": lo, "hi": hi, "queries": int(pending.size), "full": full, "chunk": c,
                "chunks": n_chunks, "cap": cap, "steps": steps, "items": float(n_it.mean()), "reruns": 0,
                "measure_s": time.perf_counter() - t_pass}
        todo = list(range(n_chunks))
        while todo:
            results = run_chunks(todo, steps, lo=lo, hi=hi, cap=cap, full=full)
            failed, worst_need, worst_items = [], 0.0, 0.0
            for ci, (idx, level, count, need, max_items, bad) in results:
                need, max_items = float(need), float(max_items)
                if bool(bad):
                    raise AssertionError("internal error: a stencil interval exceeded its static span")
                if need > cap or max_items >= 2.0**steps:  # overflow: results invalid, re-run
                    failed.append(ci)
                    worst_need, worst_items = max(worst_need, need), max(worst_items, max_items)
                    continue
                a, b = chunk_start[ci], chunk_start[ci + 1]
                rows = pending[a:b]
                out_idx[rows] = np.asarray(idx)[:b - a]
                out_level[rows] = np.asarray(level)[:b - a]
                out_count[rows] = np.asarray(count)[:b - a]
            if failed:
                info["reruns"] += 1
                if stats is not None:
                    stats["overflow_chunks"] += len(failed)
                cap = max(cap, _bucket(worst_need))
                steps = max(steps, _steps(int(worst_items)))
            todo = failed
        if stats is not None:
            info["seconds"] = time.perf_counter() - t_pass
            stats["passes"].append(info)
        pending = pending[out_level[pending] < 0]
        if pending.size and hi >= level_all + 2:
            raise AssertionError("internal error: the radii cover all data but a query has fewer than k")
        lo, hi = hi + 1, min(max(2 * hi + 1, 3), hi + LEVELS_PER_PASS, level_all + 2)
    out = (jnp.asarray(out_idx), jnp.asarray(out_level), jnp.asarray(out_count))
    idx, level, count = out
    return Neighbours(idx=idx, level=level, count=count)


def find_neighbours_nd(key, data_s, data_g, query_s, query_g, *, k=20, radius_s=0.06, radius_g=0.1,
                       growth=2 ** (1 / 3), grid=None, item_capacity=None, stats=None,
                       mesh: Mesh | None = None) -> Neighbours:
    """Neighbourhoods of paper §V-A-2 for general spaces (semantics: module docstring).

    ``data_s [N, d_s]``, ``query_s [Q, d_s]`` with ``1 <= d_s <= 10``; goals both ``None``,
    both angles ``[N]``/``[Q]`` or both vectors ``[N, d_g]``/``[Q, d_g]``. Returns
    :class:`lazyq_jax.neighbours.Neighbours` (``idx [Q, k]``, ``level [Q]``, ``count [Q]``).
    Raises ``ValueError`` before any compilation for mismatched shapes, NaN/inf,
    ``k <= 0`` or ``k > N``, bad radii or growth. ``grid``/``item_capacity``/``stats``/``mesh``:
    see :func:`build_index_nd` and :func:`search_all_nd`.
    """
    _check_params(k, radius_s, radius_g, growth)
    dc, d_s, kind, d_g = _points(data_s, data_g, "data")
    _, qd_s, qkind, qd_g = _points(query_s, query_g, "query")
    if qd_s != d_s:
        raise ValueError(f"query_s has d_s={qd_s} but data_s has d_s={d_s}")
    if qkind != kind or qd_g != d_g:
        raise ValueError(f"query goals ({qkind}, d_g={qd_g}) do not match the data goals ({kind}, d_g={d_g}) "
                         "(None: no goal; [n]: angle; [n, d_g]: vector)")
    if dc.shape[1] < k:
        raise ValueError(f"need at least k={k} data points to draw k distinct neighbours, got {dc.shape[1]}")
    index = build_index_nd(data_s, data_g, k=k, radius_s=radius_s, radius_g=radius_g, growth=growth,
                           query_sample=(query_s, query_g), grid=grid)
    return search_all_nd(index, key, query_s, query_g, item_capacity=item_capacity, stats=stats,
                         mesh=mesh)
