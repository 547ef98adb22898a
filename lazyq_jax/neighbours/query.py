"""Jittable neighbourhood queries in general spaces, for small batches (a policy step).

:func:`lazyq_jax.neighbours.nd.find_neighbours_nd` answers all of a dataset's queries
at once (host-driven passes, growth without limit).  A policy acting in a ``lax.scan``
rollout needs the same neighbourhoods ``B(s0, g0)`` (§V-A-2, semantics of
:mod:`lazyq_jax.neighbours.common`: the float32 membership formula, the smallest level
``L <= max_level`` with ``|B_L| >= k``, ``k`` distinct members drawn uniformly) for a
batch of queries at a time, inside ``jit``: :func:`build_policy_index` once per dataset,
then :func:`query_policy` at every step (pure, jittable, vmappable over stacked seeds): a
grid over a few selective axes whose per-query work is a stencil of cells with static
capacities.  (:mod:`lazyq_jax.neighbours.scan` scans all ``N`` points a query: the
reference, and the policy index's fallback.)

*Layout* (host, :func:`build_policy_index`): :mod:`lazyq_jax.neighbours.layout`'s, the data
sorted by the cells of ``m <= 4`` grid axes, chosen by :mod:`lazyq_jax.neighbours.cost` for
the stencils of the levels a policy query evaluates.  The cells of a non-periodic axis are a
power of two wide and start at a multiple of their width, so a query's cell and fraction are
exact in float32 under ``jit`` (:func:`_cells`, as the host's float64 cells of the data); the
angle's cells tile the circle.  Membership is always the exact float32 test.

*Phases with static capacities* (``index.phases``).  Phase 0 evaluates levels ``0..h_0``
(a membership word per level and item) for every query of the batch; the queries with
fewer than ``k`` members at ``h_0`` go to phase 1 (levels ``h_0+1..h_1``, the stencil of
``h_1``), in rounds, and so on up to ``max_level``.  A later phase's round has a pool of
``S_p * cap_p`` items of ``W = 32`` entries, ``S_p = max(8, ceil(frac_p Q))``, shared by
``min(Q, 8 S_p)`` slots (``_SLOT_FACTOR``: queries far from the data need high levels but
small stencils), packed smallest stencil first; queries that do not fit wait for the next
round (a ``while_loop``: one round unless the batch is unusual).  ``h_p``, ``frac_p`` and
``cap_p`` come from a sample of queries (default: data points moved by about a radius):
``frac_p`` 1.5x the estimated share still short of ``k`` (+3%), ``cap_p`` 1.1x the 99th
percentile of the exact items a query needs.  A round's work is therefore bounded by
``S_p cap_p W + 8 S_p ranges_p`` entry tests and range lookups plus ``8 S_p k (k +
log2(S_p cap_p))`` for sampling, whatever its queries (docs/performance.md: the measured
costs, ``experiments/bench_neighbours.py --cases q3,q5``).

*Overflow* (never silent).  A query whose stencil alone exceeds its phase's pool is
flagged in ``PolicyNeighbours.overflow`` and answered exactly by a scan of all data (a
``while_loop`` over the flagged queries only: no cost when nothing overflows;
``fallback=False`` leaves them ``level == -1``, still flagged).  Queries beyond
``max_level`` get ``level == -1``, ``idx == -1`` and ``count = |B_max_level|``.
Non-finite queries have no members: ``level == -1``, ``count == 0`` (and ``ValueError``
outside ``jit``).

*Randomness.*  Query ``q`` (its row) draws from a keyed hash of ``(key, q)`` only: its
sample depends on the key, its row, its coordinates and the layout, not on the other
queries or the round it runs in (the fallback scan draws another, equally uniform,
sample: ``k`` largest hashed keys).

*Padding and seeds.*  ``n_valid``: rows ``>= n_valid`` are never members (padding of
datasets stacked over seeds).  :func:`stack_policy_indices` gives several datasets'
indices one layout (the union of their grids' bounds), the largest capacities and
padded arrays, stacked on a leading axis for ``jax.vmap`` over seeds.

The lazy policy uses the policy index in every space, the paper's 2-D states with angle
goals included (the grid's own jittable query,
:func:`lazyq_jax.neighbours.grid.query_neighbours`, evaluates the stencil of ``max_level``
for every query).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from lazyq_jax.neighbours.common import (PI, W, Neighbours, _check_params, _items, _key_words, _level_tables,
                                         _member_words, _pick_level, _pow2, _query_seeds, _sample_members,
                                         wrap_angle)
from lazyq_jax.neighbours.cost import (_CAP_MARGIN, _CAP_QUANTILE, _MIN_SLOTS, _N_EST, _N_SAMPLE, _choose_layout,
                                       _estimate_levels, _fractions, _grid_p2, _grid_spec, _sample_rows,
                                       _stencil_items)
from lazyq_jax.neighbours.layout import IndexSettings, _axes_info, _points, _ranges, _sorted_columns, _table_limit
from lazyq_jax.neighbours.scan import (ScanIndex, _check_max_level, _entry_levels, _query_columns, _scan_sample,
                                       build_scan_index, query_neighbours_scan)

__all__ = ["Phase", "PolicyIndex", "PolicyNeighbours", "ScanIndex", "build_policy_index", "build_scan_index",
           "query_neighbours_scan", "query_policy", "stack_policy_indices"]


@struct.dataclass
class PolicyNeighbours(Neighbours):
    """:class:`~lazyq_jax.neighbours.Neighbours` plus ``overflow [Q]`` (bool): the query's
    stencil alone exceeded a phase's pool (the index's static capacities); its result comes
    from the full scan (exact), or is ``level == -1`` if :func:`query_policy` ran with
    ``fallback=False``.  ``overflow.sum()`` counts the scans a batch paid for."""

    overflow: jax.Array


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
class PolicyIndex(IndexSettings):
    """Data sorted by grid cell, static capacities (see module docstring); build with
    :func:`build_policy_index`, stack seeds with :func:`stack_policy_indices`."""

    cols: jax.Array  # float32 [n_cols, E + W]: sorted entries (states, wrapped angle / goal dims)
    orig: jax.Array  # int32 [E]: data row of each entry
    offsets: jax.Array  # int32 [n_cells + 1]: first entry of each cell
    n_entries: jax.Array  # int32 []: entries of this dataset (E, or fewer when padded for stacking)
    max_level: int = struct.field(pytree_node=False)
    n_rows: int = struct.field(pytree_node=False)  # rows of the (padded) dataset: idx < n_rows
    grid: tuple = struct.field(pytree_node=False)  # tuple[GridAxis]; () = scan every query
    phases: tuple = struct.field(pytree_node=False)  # tuple[Phase]; () with grid ()


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
                need = _stencil_items(grid, offsets, qcols, hi, growth).sum(axis=1)
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
        axes, widths, _ = _grid_spec(grid, _axes_info(d_s, kind, d_g, radius_s, radius_g))
        chosen, auto_his = (_grid_p2(axes, widths, col_lo, col_hi, _table_limit(n)) if axes else ()), (max_level,)
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


def _data_of(index: PolicyIndex):
    """The valid rows' columns ``[n_cols, n_valid]`` back from an index (rows ``0..n_valid-1``)."""
    e = int(index.n_entries)
    orig = np.asarray(index.orig)[:e]
    cols = np.empty((index.cols.shape[0], e), np.float32)
    cols[:, orig] = np.asarray(index.cols)[:, :e]
    return cols


_SETTINGS = ("k", "radius_s", "radius_g", "growth", "d_s", "goal", "d_g", "max_level")


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
            grid = _grid_p2([info[ax.col] for ax in first.grid], [ax.width for ax in first.grid], lo, hi,
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
                        tables=_level_tables(index.radius_s, index.radius_g, index.growth,
                                             np.arange(index.max_level + 1)))
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
