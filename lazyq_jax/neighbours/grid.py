"""The grid of the paper's case (2-D states, an angle goal): neighbourhoods ``B(s0, g0)``
of paper §V-A-2 on a grid hash, under ``jit``.

The semantics are :mod:`lazyq_jax.neighbours.common`'s float32 membership test, here with
``ds2 = dx*dx + dy*dy`` and the angle goal.

Data structure
--------------
Cells have sizes ``radius_s/4`` in x, ``radius_s/2`` in y and about ``radius_g/2``
in g (periodic). Every point is stored ``D = 5`` times, once in each *g-block*
(``D`` consecutive g-cells) that contains its g-cell; inside a block, entries are
sorted by cell id ``(y-cell, x-cell)``. A ball query at level 0 is then 5
contiguous ranges (one per y-row; the x-extent of each range is clipped to the
chord of the disk at that row), each located in O(1) through a dense table of
cell offsets. The ranges are cut into *items* of ``W = 32`` consecutive entries;
one test per item yields a 32-bit membership word, and per-query member counts
are popcount sums. Growth re-runs the search on the (few) queries with fewer
than ``k`` members with a larger stencil, evaluating several levels at once.

Sampling draws ``k`` distinct ranks in ``[0, m)`` with Floyd's algorithm and maps
each rank to its member through the prefix of popcounts and a select-in-word.

Two entry points:

* :func:`build_index` then :func:`search_all` (host-driven, exact for any number of
  queries and any level; what :func:`lazyq_jax.neighbours.find_neighbours` runs for
  this space): searches, grows until every query has ``k`` members.
  Sizes that depend on the data (number of items, queries still growing) are
  read back between passes, so it is not itself jittable.
* :func:`build_index` once, then :func:`query_neighbours` (pure, jittable, e.g.
  inside a ``lax.scan``; the lazy policy uses :mod:`lazyq_jax.neighbours.query`, whose
  phases do less work per query): static shapes whose capacities
  are bounded from the data at build time, levels ``0..index.max_level``. A query
  that would need more growth is *reported* (``level == -1``, ``idx == -1``,
  ``Neighbours.found`` false); :func:`check_found` raises on it outside ``jit``.
"""

from __future__ import annotations

import math
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from jax.sharding import Mesh, PartitionSpec as P

from lazyq_jax.neighbours.common import (PI, W, Neighbours, _bucket, _check_params, _draw_ranks, _items,
                                         _levels_to_cover, _member_words, _pick_level, _sample_members,
                                         _select_members, _steps, _without_hugepage_advice, stable_order, wrap_angle)
from lazyq_jax.neighbours.layout import _space
from lazyq_jax.parallel import AXIS, to_host

D = 5  # g-cells per g-block (each point is stored D times)
_FX, _FY, _FG = 0.25, 0.5, 0.5  # cell size / base radius in x, y, g
_CELL_SLACK = 1.001  # cells slightly above the target so the level-0 stencil stays 5 x 1


@struct.dataclass
class GridIndex:
    """Prebuilt grid hash over the data (see module docstring); build with :func:`build_index`."""

    cols: jax.Array  # float32 [3, D*N + W]: x, y, wrapped goal of the entries sorted by
    #                  (g-block, y-cell, x-cell); W padding entries at the end
    orig: jax.Array  # int32 [D*N] index of the entry in the original data
    offsets: jax.Array  # int32 [n_g*n_y*n_x + 1] first entry of each cell
    n_data: jax.Array  # int32 scalar: number of data points (entries past D*n_data are padding)
    k: int = struct.field(pytree_node=False)
    radius_s: float = struct.field(pytree_node=False)
    radius_g: float = struct.field(pytree_node=False)
    growth: float = struct.field(pytree_node=False)
    x0: float = struct.field(pytree_node=False)
    y0: float = struct.field(pytree_node=False)
    h_x: float = struct.field(pytree_node=False)
    h_y: float = struct.field(pytree_node=False)
    n_x: int = struct.field(pytree_node=False)
    n_y: int = struct.field(pytree_node=False)
    n_g: int = struct.field(pytree_node=False)
    margin: float = struct.field(pytree_node=False)  # float32 slack of the stencil
    max_level: int = struct.field(pytree_node=False)  # levels query_neighbours covers
    max_window: int = struct.field(pytree_node=False)  # entries in one range at max_level

    # The space, as the shared membership test reads it (lazyq_jax.neighbours.common).
    d_s = 2
    goal = "angle"
    d_g = 1


# ----------------------------------------------------------------------------- validation


def _check_points(s, g, what):
    _, d_s, kind, _ = _space(s, g, what)
    if (d_s, kind) != (2, "angle"):
        raise ValueError(f"{what}_s must have shape [n, 2] and {what}_g [n] (an angle), got {np.shape(s)} and "
                         f"{None if g is None else np.shape(g)}")
    s, g = np.asarray(s).astype(np.float32), np.asarray(g).astype(np.float32)
    if not (np.isfinite(s).all() and np.isfinite(g).all()):
        raise ValueError(f"{what}_s / {what}_g contain NaN or inf; remove or fix those points")
    return s, g


# ----------------------------------------------------------------------------- index


def build_index(data_s, data_g, *, k=20, radius_s=0.06, radius_g=0.1, growth=2 ** (1 / 3),
                max_level=8, bounds=None, capacity=None, max_window=None,
                on_device: bool | None = None) -> GridIndex:
    """Sort the data into the grid hash (run once per dataset).

    ``max_level`` only bounds :func:`query_neighbours` (static capacities are
    chosen from the data for that many growths); :func:`find_neighbours` grows
    without limit.

    Several datasets share compiled searches when their indices have the same
    shapes and static fields (as :mod:`lazyq_jax.study` does for its seeds): give
    them all the same ``bounds = (x_min, y_min, x_max, y_max)`` (covering every
    dataset's states), ``capacity`` (at least every dataset's size; the entry
    arrays are padded to it) and ``max_window`` (at least what each would get on
    its own: its ``max_window`` when built without one).

    ``on_device``: sort on the host (NumPy radix sorts: fastest on a CPU) or in one jitted
    program on JAX's default device (a device sort: what an accelerator wants; on a 2-core
    CPU XLA's sort of the ``5 N`` entries is ~10x slower than NumPy's).  ``None`` picks the
    device when JAX's default backend is not the CPU.  Both give bitwise the same index:
    the cells of the jitted build come from float32 thresholds that reproduce the host's
    float64 ``floor`` exactly (:func:`_cell_thresholds`).
    """
    _check_params(k, radius_s, radius_g, growth)
    if not isinstance(max_level, (int, np.integer)) or max_level < 0:
        raise ValueError(f"max_level must be an int >= 0, got {max_level!r}")
    s, g = _check_points(data_s, data_g, "data")
    n = s.shape[0]
    if n < k:
        raise ValueError(f"need at least k={k} data points to draw k distinct neighbours, got {n}")
    capacity = n if capacity is None else int(capacity)
    if capacity < n:
        raise ValueError(f"capacity={capacity} is smaller than the {n} data points")
    g = wrap_angle(g)
    x, y = s[:, 0].astype(np.float64), s[:, 1].astype(np.float64)
    if bounds is None:
        x0, y0, x1, y1 = float(x.min()), float(y.min()), float(x.max()), float(y.max())
    else:
        x0, y0, x1, y1 = map(float, bounds)
        if x.min() < x0 or y.min() < y0 or x.max() > x1 or y.max() > y1:
            raise ValueError(f"bounds={tuple(bounds)} do not cover the data (x in "
                             f"[{x.min()}, {x.max()}], y in [{y.min()}, {y.max()}])")
    h_x, h_y = _FX * radius_s * _CELL_SLACK, _FY * radius_s * _CELL_SLACK
    n_g = D * max(1, int(np.floor(2 * np.pi / (D * _FG * radius_g * _CELL_SLACK))))
    # Coarsen x/y cells if the dense offset table would dwarf the data (sparse, wide data).
    while (int((x1 - x0) / h_x) + 1) * (int((y1 - y0) / h_y) + 1) * n_g > max(4 * D * capacity, 1 << 20):
        h_x, h_y = 2 * h_x, 2 * h_y
    n_x = int((x1 - x0) / h_x) + 1
    n_y = int((y1 - y0) / h_y) + 1
    h_g = 2 * np.pi / n_g
    # float32 slack for the stencil (>> rounding of coordinates, << the 0.1% cell slack).
    margin = 2.0**-18 * (max(abs(x0), abs(y0), abs(x1), abs(y1)) + 1.0)
    # x-cells one range at max_level can span (query_neighbours' static window)
    w_cells = min(int(np.ceil(2 * (radius_s * growth**max_level * (1 + 1e-5) + margin) / h_x)) + 1, n_x)
    if on_device is None:
        on_device = jax.default_backend() != "cpu"
    if on_device:
        t_x = _cell_thresholds(x0, h_x, n_x)
        t_y = _cell_thresholds(y0, h_y, n_y)
        t_g = _cell_thresholds(-np.pi, h_g, n_g)
        cols, orig, offsets, own_window = _build_on_device(
            jnp.asarray(s), jnp.asarray(g), t_x, t_y, t_g, n_x=n_x, n_y=n_y, n_g=n_g,
            capacity=capacity, w_cells=w_cells)
    else:
        with _without_hugepage_advice():
            cols, orig, offsets, own_window = _build_on_host(s, g, x, y, x0, y0, h_x, h_y, h_g, n_x=n_x, n_y=n_y,
                                                             n_g=n_g, capacity=capacity, w_cells=w_cells)
    own_window = max(int(own_window), 1)
    if max_window is None:
        max_window = own_window
    elif max_window < own_window:
        raise ValueError(f"max_window={max_window} is below this data's {own_window}")
    return GridIndex(
        cols=cols, orig=orig, offsets=offsets,
        n_data=jnp.int32(n), k=int(k), radius_s=float(radius_s), radius_g=float(radius_g),
        growth=float(growth), x0=x0, y0=y0, h_x=h_x, h_y=h_y, n_x=n_x, n_y=n_y, n_g=n_g,
        margin=margin, max_level=int(max_level), max_window=int(max_window),
    )


def _build_on_host(s, g, x, y, x0, y0, h_x, h_y, h_g, *, n_x, n_y, n_g, capacity, w_cells):
    """The host build (NumPy radix sorts, the entries gathered on the device): ``(cols, orig,
    offsets, own_window)``; ``x``, ``y`` the states' coordinates in float64, ``g`` the
    wrapped goals."""
    ix = np.clip(np.floor((x - x0) / h_x), 0, n_x - 1).astype(np.int64)
    iy = np.clip(np.floor((y - y0) / h_y), 0, n_y - 1).astype(np.int64)
    ig = np.clip(np.floor((g.astype(np.float64) + np.pi) / h_g), 0, n_g - 1).astype(np.int64)
    # Entry copies: a point with g-cell c lies in g-blocks c-D+1 .. c (block b = cells
    # b..b+D-1).  Sort by (y-cell, x-cell) once, then stably by block (a radix sort on
    # small ints): the entries in order of (cell, point index).
    yx = iy * n_x + ix
    by_yx = stable_order(yx)
    blocks = ig[by_yx].astype(np.int32)[:, None] - np.arange(D, dtype=np.int32)[None, :]
    blocks[blocks < 0] += n_g
    blocks = blocks.ravel()
    order = stable_order(blocks, upper=n_g)
    src = by_yx[order // D]
    # Entries a cell: block b's cell yx holds the points of g-cells b .. b+D-1 in yx.
    n_yx = n_y * n_x
    per_g = np.bincount(ig * n_yx + yx, minlength=n_g * n_yx).reshape(n_g, n_yx)
    per_block = per_g.copy()
    for d in range(1, D):
        per_block += np.roll(per_g, -d, axis=0)
    offsets = np.zeros(n_g * n_yx + 1, np.int64)
    np.cumsum(per_block.ravel(), out=offsets[1:])
    own_window = _max_window(offsets, n_x, w_cells)
    cols, orig = _entries(jnp.asarray(s), jnp.asarray(g), jnp.asarray(src.astype(np.int32)),
                          capacity=capacity)
    offsets = jnp.asarray(offsets.astype(np.int32))
    return cols, orig, offsets, own_window


def _max_window(offsets, n_x, w_cells):
    """Most entries in ``w_cells`` consecutive x-cells of one row, over all rows (NumPy or,
    under ``jit``, JAX offsets).  Windows that a row's end cuts short hold no more than the
    row's last full window (the offsets grow), so only full windows are compared: slices of
    the ``[rows, n_x + 1]`` table of each row's cell starts and end, no gathers."""
    xp = jnp if isinstance(offsets, jax.Array) else np
    w = min(int(w_cells), n_x)
    rows = (offsets.shape[0] - 1) // n_x
    table = xp.concatenate([offsets[:-1].reshape(rows, n_x), offsets[n_x::n_x][:, None]], axis=1)
    return (table[:, w:] - table[:, :n_x + 1 - w]).max()


def _cell_thresholds(lo: float, h: float, n: int) -> jax.Array:
    """float32 ``t[c]`` (``c = 1 .. n-1``): the smallest float32 ``v`` with
    ``floor((float64(v) - lo) / h) >= c``, so that counting the thresholds ``<= v`` is the
    host's float64 cell ``clip(floor((v - lo) / h), 0, n - 1)`` of every float32 ``v``
    (that float64 expression is monotone in ``v``)."""
    c = np.arange(1, n, dtype=np.float64)
    t = (lo + c * h).astype(np.float32)

    def above(v):
        return np.floor((v.astype(np.float64) - lo) / h) >= c

    for _ in range(64):  # float32 rounding of lo + c * h is off by a few ulps at most
        up, down = ~above(t), above(np.nextafter(t, np.float32(-np.inf)))
        if not (up.any() or down.any()):
            return jnp.asarray(t)
        t = np.where(up, np.nextafter(t, np.float32(np.inf)),
                     np.where(down, np.nextafter(t, np.float32(-np.inf)), t))
    raise AssertionError("internal error: cell thresholds did not converge")


@partial(jax.jit, static_argnames=("n_x", "n_y", "n_g", "capacity", "w_cells"))
def _build_on_device(s, g, t_x, t_y, t_g, *, n_x, n_y, n_g, capacity, w_cells):
    """The host build's arrays in one program: the cells (thresholds), a stable device sort
    of the ``D n`` entries by cell (ties in point order: the host's order), the offsets
    (``searchsorted``) and :func:`_max_window`."""
    n = s.shape[0]
    ix = jnp.searchsorted(t_x, s[:, 0], side="right")
    iy = jnp.searchsorted(t_y, s[:, 1], side="right")
    ig = jnp.searchsorted(t_g, g, side="right")
    block = (ig[:, None] - jnp.arange(D)[None, :]) % n_g  # entry (i, d): point i, block ig - d
    cell = ((block * n_y + iy[:, None]) * n_x + ix[:, None]).ravel().astype(jnp.int32)
    cell, entry = jax.lax.sort((cell, jnp.arange(D * n, dtype=jnp.int32)), num_keys=1, is_stable=True)
    n_cells = n_g * n_y * n_x
    offsets = jnp.searchsorted(cell, jnp.arange(n_cells + 1, dtype=jnp.int32), side="left").astype(jnp.int32)
    cols, orig = _entries(s, g, entry // D, capacity=capacity)
    return cols, orig, offsets, _max_window(offsets, n_x, w_cells)


@partial(jax.jit, static_argnames=("capacity",))
def _entries(s, g, src, *, capacity):
    """The index's entry arrays from ``src`` (int32 ``[D n]``: the point of each entry, in
    entry order): ``cols`` (x, y and wrapped goal of each entry; zeros past ``D n``, up to
    ``D capacity + W``: the ``W`` more make every item one contiguous slice) and ``orig``
    (``src``, zeros past ``D n``: never addressed, every cell range ends before).  A device
    gather in both builds: on the host's CPU it is twice as fast as NumPy's fancy indexing
    and the copy of its result (0.1 s against 0.2 s at N = 1M, 2 cores)."""
    cols = jnp.zeros((3, D * capacity + W), jnp.float32).at[:, :src.shape[0]].set(
        jnp.stack([s[:, 0], s[:, 1], g])[:, src])
    orig = jnp.zeros((D * capacity,), jnp.int32).at[:src.shape[0]].set(src)
    return cols, orig


# ----------------------------------------------------------------------------- jitted core


def _stencil(index: GridIndex, level: int):
    """Static stencil at ``level``: expanded radii, y-rows and g-blocks per query."""
    r_s = index.radius_s * index.growth**level * (1 + 1e-5) + index.margin
    r_g = index.radius_g * index.growth**level * (1 + 1e-5) + 1e-5
    n_rows = min(int(np.ceil(2 * r_s / index.h_y)) + 1, index.n_y)
    n_blocks = int(np.ceil((np.ceil(r_g * index.n_g / np.pi) + 1) / D))
    full_g = n_blocks * D > index.n_g
    return r_s, r_g, n_rows, (index.n_g // D if full_g else n_blocks), full_g


def _plan(index: GridIndex, qx, qy, qg, level: int):
    """Candidate ranges ``(start, length)`` ``[Q, R]`` of the level-``level`` stencil (exact cover)."""
    r_s, r_g, n_rows, n_blocks, full_g = _stencil(index, level)
    h_g = 2 * np.pi / index.n_g
    f32 = jnp.float32
    iy_lo = jnp.clip(jnp.floor((qy - f32(r_s) - f32(index.y0)) / f32(index.h_y)), 0, index.n_y - 1)
    iy = iy_lo.astype(jnp.int32)[:, None] + jnp.arange(n_rows, dtype=jnp.int32)  # [Q, rows]
    y_lo = f32(index.y0) + iy.astype(f32) * f32(index.h_y)
    dmin = jnp.maximum(jnp.maximum(y_lo - qy[:, None], qy[:, None] - (y_lo + f32(index.h_y))), 0.0)
    dmin = jnp.maximum(dmin - f32(index.margin), 0.0)
    hw2 = f32(r_s) ** 2 - dmin * dmin
    row_ok = (hw2 > 0) & (iy < index.n_y)
    hw = jnp.sqrt(jnp.maximum(hw2, 0.0))
    qxc = qx[:, None]
    ix_lo = jnp.clip(jnp.floor((qxc - hw - f32(index.x0)) / f32(index.h_x)), 0, index.n_x - 1).astype(jnp.int32)
    ix_hi = jnp.clip(jnp.floor((qxc + hw - f32(index.x0)) / f32(index.h_x)), 0, index.n_x - 1).astype(jnp.int32)
    if full_g:
        g_first = jnp.zeros_like(qg, dtype=jnp.int32)
    else:
        g_first = jnp.floor((qg - f32(r_g) + PI) / f32(h_g)).astype(jnp.int32)
    blocks = jnp.mod(g_first[:, None] + D * jnp.arange(n_blocks, dtype=jnp.int32), index.n_g)  # [Q, B]
    row = (blocks[:, :, None] * index.n_y + jnp.minimum(iy, index.n_y - 1)[:, None, :]) * index.n_x
    start = index.offsets[row + ix_lo[:, None, :]]
    end = index.offsets[row + ix_hi[:, None, :] + 1]
    length = jnp.where(row_ok[:, None, :], end - start, 0)
    q = qx.shape[0]
    return start.reshape(q, -1), length.reshape(q, -1)


def _search(index: GridIndex, seed, qx, qy, qg, *, lo: int, hi: int, n_items: int, steps: int):
    """Levels ``lo..hi`` for every query (stencil of level ``hi``), then sampling at that level.

    ``seed``: uint32 ``[Q]``, the random bits of each query's sample.

    ``n_items`` must be at least the total number of items; ``steps`` at least the
    bit length of the largest number of items of one query (:func:`_steps`). Returns ``(idx, level, count)``
    with ``level == -1`` (``idx == -1``, ``count`` at level ``hi``) where ``|B_hi| < k``.
    """
    k = index.k
    start, length = _plan(index, qx, qy, qg, hi)
    item_q, item_start, item_valid, first, n_q = _items(start, length, n_items)
    words = _member_words(index, jnp.stack([qx, qy, qg]), item_q, item_start, item_valid, lo, hi)
    found, li, level, m = _pick_level(words, item_q, qx.shape[0], k, lo)
    idx = _sample_members(index.orig, words, li, found, m, seed, item_q, item_start, first, n_q, k=k,
                          steps=steps)
    return idx, level.astype(jnp.int32), m.astype(jnp.int32)


def _sharded(fn, mesh, n_replicated: int, n_split: int):
    """``fn`` over one contiguous block of the split arguments per device of ``mesh``
    (``shard_map``: the first ``n_replicated`` arguments, e.g. the index, replicated; the
    results concatenated), or ``fn`` itself without a mesh."""
    if mesh is None:
        return fn
    return jax.shard_map(fn, mesh=mesh, in_specs=(*[P()] * n_replicated, *[P(AXIS)] * n_split),
                         out_specs=P(AXIS), check_vma=False)


# A pass of search_all is three programs, so that what each one's later gathers read is
# materialised (on the CPU, XLA fuses cheap maps of earlier results into every gather that
# reads them and recomputes them there, chains of dependent random gathers: one program for
# the whole pass ran 0.8 s at 1M queries on 2 cores, the three 0.6 s;
# lax.optimization_barrier does not stop that fusion on the CPU):
#   _plan_pass:   the queries gathered, their random bits, the stencil's ranges and items a query
#                 (read back to size the next program exactly);
#   _rank_pass:   items, membership words, level, each item's word and popcount prefix, and
#                 the k ranks of every query (common._draw_ranks);
#   _select_pass: each rank's member (common._select_members); then _unsort (the first pass:
#                 every query) or _write (a later pass: a few) puts them in the queries' rows.


@partial(jax.jit, static_argnames=("level", "mesh"))
def _plan_pass(index: GridIndex, key, qs, qg, sub, *, level, mesh=None):
    """The queries ``sub`` (indices; padding entries ``Q`` search a copy of query ``Q - 1``):
    their columns and random bits (query ``q`` draws ``bits(key, (Q,))[q]``, so its sample
    does not depend on which other queries share its pass), the candidate ranges of the
    level-``level`` stencil and the items of each query."""
    read = jnp.minimum(sub, qs.shape[0] - 1)
    seeds = jax.random.bits(key, (qs.shape[0],), jnp.uint32)[read]
    qx, qy, g = qs[read, 0], qs[read, 1], qg[read]

    def plan(index, qx, qy, g):
        start, length = _plan(index, qx, qy, g, level)
        return start, length, ((length + W - 1) // W).sum(axis=1)

    return (seeds, qx, qy, g), *_sharded(plan, mesh, 1, 3)(index, qx, qy, g)


@partial(jax.jit, static_argnames=("lo", "hi", "n_items", "mesh"))
def _rank_pass(index: GridIndex, queries, start, length, *, lo, hi, n_items, mesh=None):
    """Levels ``lo..hi`` of every query (its stencil of level ``hi`` from :func:`_plan_pass`)
    and its ``k`` ranks; ``n_items``: at least the items of the queries (of one device's
    block with a ``mesh``)."""
    k = index.k

    def rank(index, seed, qx, qy, g, start, length):
        item_q, item_start, item_valid, first, n_q = _items(start, length, n_items)
        words = _member_words(index, jnp.stack([qx, qy, g]), item_q, item_start, item_valid, lo, hi)
        found, li, level, m = _pick_level(words, item_q, qx.shape[0], k, lo)
        word, prefix, ranks = _draw_ranks(words, li, found, m, seed, item_q, k=k)
        return (word, prefix, item_start), (ranks, found, first, n_q, level.astype(jnp.int32),
                                            m.astype(jnp.int32))

    return _sharded(rank, mesh, 1, 6)(index, *queries, start, length)


@partial(jax.jit, static_argnames=("steps", "mesh"))
def _select_pass(index: GridIndex, items, per_query, *, steps, mesh=None):
    """Each rank's member (``steps``: at least the bit length of the most items of a query):
    ``(idx, level, count)`` of the pass's queries, in the pass's order."""

    def select(orig, word, prefix, item_start, ranks, found, first, n_q):
        return _select_members(orig, word, prefix, ranks, found, item_start, first, n_q, steps=steps)

    ranks, found, first, n_q, level, m = per_query
    return _sharded(select, mesh, 1, 7)(index.orig, *items, ranks, found, first, n_q), level, m


@jax.jit
def _unsort(results, inv):
    """The first pass's results (every query, in cell order) in the queries' order: row ``q``
    is row ``inv[q]`` (``inv[q]`` past the results for rows that are not searched: zeros).  A
    gather, where writing them back with a scatter would be ~1.5x slower on the CPU."""
    return tuple(jnp.concatenate([r, jnp.zeros_like(r[:1])]).at[inv].get(mode="clip") for r in results)


@partial(jax.jit, donate_argnums=(0,))
def _write(out, sub, results):
    """A later pass's results into ``out`` at the rows ``sub`` (padding entries ``Q`` are
    dropped, so every row has one writer)."""
    return tuple(o.at[sub].set(r, mode="drop") for o, r in zip(out, results))


def query_neighbours(index: GridIndex, key, query_s, query_g) -> Neighbours:
    """Neighbours of a batch of queries from a prebuilt index: pure and jittable.

    Static capacities come from the data (``index.max_window``), so nothing is
    dropped: every query with ``|B_L| >= k`` for some ``L <= index.max_level`` gets
    its exact level and an exact sample. A query needing more growth gets
    ``level == -1`` and ``idx == -1`` (see :func:`check_found`;
    :func:`find_neighbours` has no such limit). The work is that of the
    ``max_level`` stencil for every query: meant for small batches
    (:func:`lazyq_jax.neighbours.query.query_policy` does less work per query where
    most queries need few growths). Batch the queries rather than ``vmap`` over this
    function.
    """
    shape_g = None if query_g is None else np.shape(query_g)
    if np.ndim(query_s) != 2 or np.shape(query_s)[1] != 2 or shape_g != np.shape(query_s)[:1]:
        raise ValueError(f"query_s must be [Q, 2] and query_g [Q]; got {np.shape(query_s)} and {shape_g}")
    q = np.shape(query_s)[0]
    qs = jnp.asarray(query_s, jnp.float32)
    _, _, n_rows, n_blocks, _ = _stencil(index, index.max_level)
    per_query = n_rows * n_blocks * (-(-index.max_window // W))
    seed = jax.random.bits(key, (q,), jnp.uint32)
    idx, level, count = _search(index, seed, qs[:, 0], qs[:, 1], wrap_angle(jnp.asarray(query_g)),
                                lo=0, hi=index.max_level, n_items=max(q * per_query, 1),
                                steps=_steps(per_query))
    return Neighbours(idx=idx, level=level, count=count)


def check_found(nb: Neighbours) -> Neighbours:
    """Raise (outside ``jit``) if any query of :func:`query_neighbours` needed more growth."""
    missing = int(np.sum(np.asarray(nb.level) < 0))
    if missing:
        raise ValueError(f"{missing} queries need more than max_level growths; rebuild the index with a "
                         "larger max_level or use find_neighbours (no limit)")
    return nb


def search_all(index: GridIndex, key, query_s, query_g, *, mesh: Mesh | None = None,
               n_queries: int | None = None) -> Neighbours:
    """Exact neighbours of any number of queries (host-driven passes; not jittable).

    Pass 1 evaluates level 0 for all queries (sorted by cell for locality); the
    queries still short of ``k`` members are compacted and searched again with
    the stencils of levels ``1..3``, ``4..7``, ``8..15``, ... until the radius
    covers all data, where ``|B| = N >= k``. Item counts are read back between
    passes to size each pass exactly (rounded by :func:`_bucket`).

    A query's sample depends only on ``key`` and its position in ``query_s``.
    ``mesh`` (see :mod:`lazyq_jax.parallel`): every pass splits its queries over
    the devices, the data (index) is replicated; the result is bitwise the same.

    ``n_queries``: only the first ``n_queries`` rows are searched; the rest are
    padding (results 0), so that datasets of different sizes padded to one length
    share the compiled passes.  A searched query's result does not depend on the
    padding.
    """
    qs, qg = _check_points(query_s, query_g, "query")
    qg = wrap_angle(qg)
    n_q = qs.shape[0]
    n_real = n_q if n_queries is None else int(n_queries)
    if not 0 <= n_real <= n_q:
        raise ValueError(f"n_queries={n_queries} must lie in [0, {n_q}]")
    k = index.k
    if n_q == 0:
        z = jnp.zeros((0,), jnp.int32)
        return Neighbours(idx=jnp.zeros((0, k), jnp.int32), level=z, count=z)
    # Query order, for locality only (a query's result does not depend on it): by g-cell, then
    # y-cell, the rows of the data layout (a stencil reads ~5 rows of one g-block, a few KB
    # each at the paper's density, so the order within a row hardly matters); in float32, and
    # one 16-bit radix pass where the key fits.
    f32 = np.float32
    row = (np.clip(np.floor((qg[:n_real] + PI) * f32(index.n_g / (2 * np.pi))), 0, index.n_g - 1).astype(np.int32)
           * index.n_y + np.clip(np.floor((qs[:n_real, 1] - f32(index.y0)) / f32(index.h_y)), 0,
                                 index.n_y - 1).astype(np.int32))
    order = stable_order(row, upper=index.n_g * index.n_y).astype(np.int32)
    # Level at which the radii cover everything: |B| = N there.
    real = qs[:n_real] if n_real else qs[:1]
    lo_x, lo_y = min(real[:, 0].min(), index.x0), min(real[:, 1].min(), index.y0)
    # the data lie below the grid's far edges (x0 + n_x h_x, y0 + n_y h_y): a bound, not read off
    # the entries (two reductions over the D N entries)
    hi_x = max(real[:, 0].max(), index.x0 + index.n_x * index.h_x)
    hi_y = max(real[:, 1].max(), index.y0 + index.n_y * index.h_y)
    level_all = _levels_to_cover((math.hypot(hi_x - lo_x, hi_y - lo_y), math.pi), (index.radius_s, index.radius_g),
                                 index.growth)
    # The passes do not read max_level/max_window (query_neighbours' capacities): indices that
    # differ only there share compiled passes.
    index = index.replace(max_level=0, max_window=1)
    out = None  # the first pass writes every row
    pending, lo, hi, p = order, 0, 0, 0
    qs_j, qg_j = jnp.asarray(qs), jnp.asarray(qg)
    d = 1 if mesh is None else mesh.size
    while pending.size:
        # Pad the pending queries (pass 1: all n_q rows, padding included; later, few,
        # passes: to a power of two, so that datasets of similar sizes share compiled
        # passes) to a multiple of the device count with the out-of-range index n_q,
        # whose results are dropped.
        size = -(-(n_q if p == 0 else 1 << (pending.size - 1).bit_length()) // d) * d
        sub = np.concatenate([pending, np.full(size - pending.size, n_q, np.int32)])
        sub_j = jnp.asarray(sub)
        queries, start, length, n_it = _plan_pass(index, jax.random.fold_in(key, p), qs_j, qg_j, sub_j,
                                                  level=hi, mesh=mesh)
        n_it = to_host(n_it)  # (on a mesh of several processes: from every process)
        items, per_query = _rank_pass(index, queries, start, length, lo=lo, hi=hi, mesh=mesh,
                                      n_items=_bucket(n_it.reshape(d, -1).sum(axis=1).max(), coarse=p > 0))
        results = _select_pass(index, items, per_query, steps=_steps(n_it.max()), mesh=mesh)
        if p == 0:
            inv = np.full(n_q, size, np.int32)  # rows past n_real: the zero row
            inv[pending] = np.arange(pending.size, dtype=np.int32)
            out = _unsort(results, jnp.asarray(inv))
        else:
            out = _write(out, sub_j, results)
        pending = pending[to_host(out[1])[pending] < 0]
        if pending.size and hi >= level_all:
            raise AssertionError("internal error: radius covers all data but fewer than k members")
        lo, hi, p = hi + 1, min(max(2 * hi + 1, 3), level_all), p + 1
    if out is None:  # nothing searched (n_queries=0): every row is padding
        out = (jnp.zeros((n_q, k), jnp.int32), jnp.zeros((n_q,), jnp.int32), jnp.zeros((n_q,), jnp.int32))
    idx, level, count = out
    return Neighbours(idx=idx, level=level, count=count)

