"""Exact neighbourhoods ``B(s0, g0)`` (paper §V-A-2) for general state and goal spaces:
every query of a dataset, host-driven passes, growth without limit.

Generalises :mod:`lazyq_jax.neighbours.grid` (states ``[N, 2]``, angle goals) to states
``s[N, d_s]`` with ``1 <= d_s <= 10`` and goals that are an angle ``g[N]``, a vector
``g[N, d_g]`` (``1 <= d_g <= 10``) or absent (``None``).  The semantics are the float32
membership test of :mod:`lazyq_jax.neighbours.common`; the layout (the data sorted by the
cells of a few axes, a query's stencil as ranges, the cost model) is
:mod:`lazyq_jax.neighbours.layout`'s, chosen here by the work of the level-0 stencil of
sample queries (items plus ``_RANGE_COST`` a range) over cell widths of 0.25-2 radii and
replication 1 or the first axis's span, or no grid (a full scan).

*Membership words and sampling* are the shared core of :mod:`lazyq_jax.neighbours.common`.

*Host-driven growth* (as :func:`lazyq_jax.neighbours.grid.search_all`): pass 1 tests level
0 for all queries (sorted by cell key for locality); queries still short of ``k`` are
searched again with levels ``1..3``, ``4..7``, ``8..15``, ... (at most 16 levels a pass,
the stencil of the highest) until the radii cover all data (``|B| = N >= k``).

*Capacities and overflow* (jax-md ``partition.py`` style). Each pass first *measures*
(a cheap jitted pass over the stencils only) the exact number of items of every
pending query, then *allocates*: the cell-sorted queries are packed greedily into
chunks of at most ``limit`` items (about ``chunk_items``) and ``c`` queries (a multiple of
256), both sized so that about as many chunks as either bound alone needs are filled: a
chunk costs its static shapes, not its fill.  ``cap`` (static items a chunk) is the largest
chunk's need rounded up to 4 significant bits, so that few variants compile; the search
steps come from the largest per-query count.  Every chunk reports the items it needed and
its largest per-query count; a chunk that did not fit (only possible with
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
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from jax.sharding import Mesh, PartitionSpec as P

from lazyq_jax.neighbours.common import (Neighbours, W, _bucket, _check_params, _draw_ranks, _items, _key_words,
                                         _levels_to_cover, _member_words, _pick_level, _pow2, _query_seeds,
                                         _select_members, _steps, stable_order)
from lazyq_jax.neighbours.cost import _MAX_REP, _choose_grid, _coarsen, _grid_spec
from lazyq_jax.neighbours.layout import (GridAxis, IndexSettings, _axes_info, _check_match, _n_ranges, _points,
                                         _query_cells, _ranges, _sorted_columns, _space, _use_full_scan,
                                         membership_level_reference)
from lazyq_jax.parallel import AXIS, put, replicated, sharded, to_host

__all__ = ["GridAxis", "NDIndex", "build_index_nd", "find_neighbours_nd", "membership_level_reference",
           "search_all_nd"]

LEVELS_PER_PASS = 16
MAX_LEVELS = 4096  # growths needed to cover all data; beyond: growth too close to 1
_CHUNK_ITEMS = 1 << 20  # target items per chunk
_MEASURE_ENTRIES = 1 << 24  # ranges a measuring block (its [B, R] arrays: 64 MB each)


@struct.dataclass
class NDIndex(IndexSettings):
    """Data sorted by grid cell (see module docstring); build with :func:`build_index_nd`."""

    cols: jax.Array  # float32 [n_cols, E + W]: state dims, then the wrapped angle or the goal dims
    orig: jax.Array  # int32 [E]: original index of each sorted entry (E = N * replication)
    offsets: jax.Array  # int32 [n_cells + 1]: first entry of each cell
    grid: tuple = struct.field(pytree_node=False)  # tuple[GridAxis], slowest first; () = full scan
    col_lo: tuple = struct.field(pytree_node=False)  # per column data min (host floats)
    col_hi: tuple = struct.field(pytree_node=False)
    n_points: int = struct.field(pytree_node=False)  # N

    @property
    def n_entries(self) -> int:
        return int(self.orig.shape[0])


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
        axes, widths, rep = _grid_spec(grid, _axes_info(d_s, kind, d_g, radius_s, radius_g), _MAX_REP)
        chosen = _coarsen(axes, widths, col_lo, col_hi, n, rep) if axes else ()
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


def _levels_to_cover_nd(index: NDIndex, qcols) -> int:
    """A level whose radii cover every (data, query) pair (so ``|B| = N >= k`` there)."""
    lo = np.minimum(np.asarray(index.col_lo), qcols.min(axis=1))
    hi = np.maximum(np.asarray(index.col_hi), qcols.max(axis=1))
    span = hi.astype(np.float64) - lo.astype(np.float64)
    diag_s = float(np.sqrt(np.sum(span[:index.d_s] ** 2)))
    diag_g = {"angle": math.pi, "none": 0.0}.get(index.goal, float(np.sqrt(np.sum(span[index.d_s:] ** 2))))
    return _levels_to_cover((diag_s, diag_g), (index.radius_s, index.radius_g), index.growth)


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
    _check_match((index.d_s, index.goal, index.d_g), (d_s, kind, d_g))
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
    level_all = _levels_to_cover_nd(index, qcols[:, :max(n_real, 1)])
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
    return Neighbours(idx=jnp.asarray(out_idx), level=jnp.asarray(out_level), count=jnp.asarray(out_count))


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
    n, *space = _space(data_s, data_g, "data")
    _check_match(space, _space(query_s, query_g, "query")[1:])
    if n < k:
        raise ValueError(f"need at least k={k} data points to draw k distinct neighbours, got {n}")
    index = build_index_nd(data_s, data_g, k=k, radius_s=radius_s, radius_g=radius_g, growth=growth,
                           query_sample=(query_s, query_g), grid=grid)
    return search_all_nd(index, key, query_s, query_g, item_capacity=item_capacity, stats=stats,
                         mesh=mesh)
