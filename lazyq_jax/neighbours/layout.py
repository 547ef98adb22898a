"""The sorted-cell layout that :mod:`~lazyq_jax.neighbours.nd` (every query of a dataset) and
:mod:`~lazyq_jax.neighbours.query` (the policy's bounded per-step query) share: the point sets
(validated columns), the grid axes, the data sorted by cell with a dense table of cell
offsets and each query's stencil as ranges of sorted entries (which layout:
:mod:`~lazyq_jax.neighbours.cost`).  Membership is never decided here: the grid only has to
cover ``B_L``; the float32 test of :mod:`~lazyq_jax.neighbours.common` decides.

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
see ``experiments/bench_neighbours.py --cases 2a,3a,4a,6a,3v``).

*Float safety.* Data cells are assigned in float64 on the host; each query's cell
position is split on the host into an integer and a fraction, so the stencil
arithmetic under ``jit`` works on small numbers; the stencil is widened by a relative
``1e-5`` of the radius (``+1e-5`` rad for the angle, whose float32 wrap-around is off
by ~1e-6) plus ``1e-4`` cells, far above the float32 error of the test. The grid only
has to cover ``B_L``; membership is always the float32 formula.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np
from flax import struct

from lazyq_jax.neighbours.common import (
    TWO_PI,
    W,
    _level_tables,
    _without_hugepage_advice,
    stable_order,
    wrap_angle,
)

MAX_DIM = 10  # largest d_s and d_g
MAX_GRID_AXES = 4
_REL_SLACK = 1e-5  # stencil widening, relative to the radius
_ANGLE_SLACK = 1e-5  # absolute, radians
_CELL_SLACK = 1e-4  # absolute, cells
_INT_CLIP = float(1 << 30)


@struct.dataclass
class IndexSettings:
    """The static settings every general index carries (:class:`~lazyq_jax.neighbours.nd.NDIndex`,
    the policy's and the scan's): ``k``, the radii and growth of §V-A-2 and the space."""

    k: int = struct.field(pytree_node=False)
    radius_s: float = struct.field(pytree_node=False)
    radius_g: float = struct.field(pytree_node=False)
    growth: float = struct.field(pytree_node=False)
    d_s: int = struct.field(pytree_node=False)
    goal: str = struct.field(pytree_node=False)  # "angle" | "vector" | "none"
    d_g: int = struct.field(pytree_node=False)  # 1 for angle, 0 for none


@dataclass(frozen=True)
class GridAxis:
    """One grid axis (static): data column ``col``, cells ``[origin + i*width, origin + (i+1)*width)``."""

    col: int  # column of the index's cols
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




# ----------------------------------------------------------------------------- point sets


def _space(s, g, what):
    """``(n, d_s, goal kind, d_g)`` of one point set from its shapes alone (no copy): states
    ``[n, d_s]``, goals ``None``, an angle ``[n]`` or a vector ``[n, d_g]``."""
    shape, shape_g = np.shape(s), None if g is None else np.shape(g)
    if len(shape) != 2 or not 1 <= shape[1] <= MAX_DIM:
        raise ValueError(f"{what}_s must have shape [n, d_s] with 1 <= d_s <= {MAX_DIM}, got {shape}")
    n, d_s = shape
    if shape_g is None:
        return n, d_s, "none", 0
    if shape_g == (n,):
        return n, d_s, "angle", 1
    if len(shape_g) == 2 and shape_g[0] == n and 1 <= shape_g[1] <= MAX_DIM:
        return n, d_s, "vector", shape_g[1]
    raise ValueError(f"{what}_g must be None, an angle [{n}] or a vector [{n}, d_g] with "
                     f"1 <= d_g <= {MAX_DIM} to match {what}_s {shape}, got {shape_g}")


def _points(s, g, what):
    """Validate one point set; returns ``(cols float32 [n_cols, n], d_s, goal kind, d_g)``."""
    n, d_s, kind, d_g = _space(s, g, what)
    s = np.asarray(s).astype(np.float32)
    gcols = np.zeros((0, n), np.float32)
    if g is not None:
        g = np.asarray(g).astype(np.float32)
        if not np.isfinite(g).all():
            raise ValueError(f"{what}_g contains NaN or inf; remove or fix those points")
        gcols = wrap_angle(g)[None, :] if kind == "angle" else g.T
    if not np.isfinite(s).all():
        raise ValueError(f"{what}_s contains NaN or inf; remove or fix those points")
    cols = np.ascontiguousarray(np.concatenate([s.T, gcols], axis=0), dtype=np.float32)
    return cols, d_s, kind, d_g


def _check_match(data, query):
    """Raise unless the queries' space ``(d_s, goal kind, d_g)`` is the data's."""
    (d_s, kind, d_g), (qd_s, qkind, qd_g) = data, query
    if qd_s != d_s:
        raise ValueError(f"query_s has d_s={qd_s} but the data have d_s={d_s}")
    if (qkind, qd_g) != (kind, d_g):
        raise ValueError(f"query goals ({qkind}, d_g={qd_g}) do not match the data goals ({kind}, d_g={d_g}) "
                         "(None: no goal; [n]: angle; [n, d_g]: vector)")


# ----------------------------------------------------------------------------- reference


def membership_level_reference(data_s, data_g, query_s, query_g, *, radius_s=0.06, radius_g=0.1,
                               growth=2 ** (1 / 3), max_level=400):
    """NumPy float32 reference: ``lam [Q, N]``, the smallest ``L`` with the point in ``B_L``.

    ``level = k-th smallest lam`` per row and ``count = (lam <= level).sum()``. Memory
    ``O(Q N)``: for tests and benchmark checks.
    """
    dc, d_s, kind, d_g = _points(data_s, data_g, "data")
    qc, *_ = _points(query_s, query_g, "query")
    r2s, rg, rg2 = _level_tables(radius_s, radius_g, growth, np.arange(max_level + 1))
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

# ----------------------------------------------------------------------------- cost model pieces (host)


def _axes_info(d_s, kind, d_g, radius_s, radius_g):
    info = [(c, "s", False, radius_s) for c in range(d_s)]
    if kind == "angle":
        info.append((d_s, "g", True, radius_g))
    elif kind == "vector":
        info += [(d_s + c, "g", False, radius_g) for c in range(d_g)]
    return info

def _table_limit(n):
    return max(2 * n, 1 << 16)


def _offsets(grid, key):
    n_cells = math.prod(ax.n_key for ax in grid)
    offsets = np.zeros(n_cells + 1, np.int64)
    np.cumsum(np.bincount(key, minlength=n_cells), out=offsets[1:])
    return offsets


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


