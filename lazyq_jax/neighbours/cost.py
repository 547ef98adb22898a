"""How a layout of :mod:`lazyq_jax.neighbours.layout` is chosen (host, NumPy): one cost model,
two uses.  A candidate is a grid (axes, cell widths) over the data; its work is what its
stencils cost sample queries, measured on a data subsample: items of ``W`` entries
(:func:`_stencil_items`) plus ``_RANGE_COST`` a range, or a full scan where a stencil has more
ranges than a scan has items.  The choice changes speed only, never a neighbourhood.

Common to both: axes ordered by their measured selectivity (:func:`_axis_order`: the data
within a radius of sample queries), prefixes of 1-4 axes (the angle, periodic, first), cell
widths 0.25-2 radii (:func:`_candidate_axes`), each candidate's exact stencils for ~256
sample queries on a 64k-point subsample, and "no grid" (a full scan) as a candidate.

* :func:`_choose_grid` (:mod:`~lazyq_jax.neighbours.nd`, every query of a dataset): the
  level-0 stencil, widths in radii, replication of the first axis.
* :func:`_choose_layout` (:mod:`~lazyq_jax.neighbours.query`, the policy's per-step query):
  the phases of levels a policy query evaluates, power-of-two widths (exact cells under
  ``jit``), each phase's pool at the 99th percentile of its items, plus slots and phases.
"""

from __future__ import annotations

import math

import numpy as np

from lazyq_jax.neighbours.common import W
from lazyq_jax.neighbours.layout import (MAX_GRID_AXES, GridAxis, _axes_info, _n_ranges, _offsets, _query_cells,
                                         _ranges, _table, _table_limit, _use_full_scan, membership_level_reference)

_RANGE_COST = 0.25  # items' worth of work a stencil range costs
_SAMPLE = 256  # nd: sample queries of the cost model
_MAX_REP = 8  # nd: copies of each point when the first grid axis is replicated
_MAX_ENTRIES = 1 << 27  # nd: bound on N * replication
_MIN_SLOTS = 8  # the policy: slots of a later phase's round, at least
_REF_BATCH = 320  # batch size the cost model assumes (a rollout's episodes)
_CAP_QUANTILE = 99.0
_CAP_MARGIN = 1.1
_SLOT_MARGIN, _SLOT_EXTRA = 1.5, 0.03
_SLOT_COST = 4.0  # items' worth of work a slot costs beyond its items (sampling)
_PHASE_COST = 0.15  # an extra phase must save 15% (each adds ~2-3 s of compile on a 2-core CPU)
_N_SAMPLE = 512  # sample queries for capacities
_N_EST = 256  # sample queries for the level and cost estimates
_EST_SUB = 1 << 16  # data subsample of the estimates


def _axis_order(info, sub, qs, scale=1.0):
    """The axes of ``info`` (``(col, block, periodic, radius)``) by selectivity, most selective
    first: the mean fraction of the data subsample ``sub`` within ``radius * scale`` of the
    sample queries ``qs`` along the axis."""
    sel = []
    for col, _block, periodic, radius in info:
        x = np.sort(sub[col].astype(np.float64))
        r = radius * scale
        if periodic:
            x = np.concatenate([x - 2 * np.pi, x, x + 2 * np.pi])
        q = qs[col].astype(np.float64)
        sel.append(float(((np.searchsorted(x, q + r) - np.searchsorted(x, q - r)) / sub.shape[1]).mean()))
    return [info[i] for i in np.argsort(sel, kind="stable")]


def _candidate_axes(order):
    """The candidate grids of both cost models: ``(axes, widths in radii)`` for prefixes of 1-4
    axes of ``order`` (the angle first; never last: the contiguous axis), the last axis's
    cells 0.25-1 radii, the others' 0.5-2 and no narrower."""
    for m in range(1, min(MAX_GRID_AXES, len(order)) + 1):
        axes = order[:m]
        axes = [a for a in axes if a[2]] + [a for a in axes if not a[2]]  # periodic first
        if axes[-1][2]:
            continue  # the contiguous (last) axis must not be periodic
        for h_other in (0.5, 1.0, 2.0):
            for h_last in (0.25, 0.5, 1.0):
                if h_last <= h_other and (m > 1 or h_other == 1.0):
                    yield axes, [h_other] * (m - 1) + [h_last]


def _stencil_items(grid, offsets, qcols, level, growth, scale=1.0):
    """Items (of ``W`` entries) of each range of each query's level-``level`` stencil,
    ``[Q, R]``: exact with the full table (``scale`` 1), estimated from a subsample's table
    (``scale`` = data / subsample) otherwise."""
    ip, fr, _ = _query_cells(grid, qcols)
    _, length, _ = _ranges(np, grid, offsets, ip.astype(np.int64), fr, level, growth)
    return np.ceil(length * scale / W)


# ----------------------------------------------------------------------------- the policy's layout


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


def _grid_p2(axes, widths, col_lo, col_hi, n_limit):
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


def _fractions(his, levels):
    """Slot fraction of each phase after the first: 1.5x the estimated share of queries still
    short of ``k`` after the previous phase, +3%."""
    return [1.0] + [min(1.0, _SLOT_MARGIN * float(np.mean(levels > h)) + _SLOT_EXTRA) for h in his[:-1]]


def _schedule_cost(grid, his, fracs, need_q, growth, n_entries):
    """Work per query (in items) of a schedule: every phase's pool, ranges and slots."""
    cost = 0.0
    for hi, frac in zip(his, fracs):
        if _use_full_scan(grid, hi, growth, n_entries):  # more ranges than a scan has items
            return math.inf
        r = _n_ranges(grid, hi, growth)
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
    # Axes by selectivity: the fraction of the data within the typical radius of a query.
    order = _axis_order(_axes_info(d_s, kind, d_g, radius_s, radius_g), sub, est_q, growth**h_ref)
    best, best_cost = ((), ()), n / W + _SLOT_COST  # the scan
    seen = set()
    for axes, rel in _candidate_axes(order):
        grid = _grid_p2(axes, [h * a[3] * growth**h_ref for h, a in zip(rel, axes)], col_lo, col_hi,
                          _table_limit(n))
        if grid in seen:
            continue
        seen.add(grid)
        offsets = _offsets(grid, _table(grid, sub)[0])
        need_q = {}
        for sched in schedules:
            for h in sched:
                if h not in need_q:
                    items = _stencil_items(grid, offsets, est_q, h, growth, scale).sum(axis=1)
                    need_q[h] = float(np.percentile(items, _CAP_QUANTILE))
            cost = _schedule_cost(grid, sched, _fractions(sched, levels), need_q, growth, n)
            if cost < best_cost * 0.98:
                best, best_cost = (grid, sched), cost
    return best[0], best[1], levels


# ----------------------------------------------------------------------------- nd's grid


def _grid_radii(axes, widths, col_lo, col_hi, rep=1):
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


def _coarsen(axes, widths, col_lo, col_hi, n, rep=1):
    """Double the cell widths until the offset table fits (sparse, wide data)."""
    for _ in range(80):
        grid = _grid_radii(axes, widths, col_lo, col_hi, rep)
        if math.prod(ax.n_key for ax in grid) <= _table_limit(n):
            return grid
        widths = [2 * h for h in widths]
    return None


def _grid_cost(grid, cols_sub, n_data, qcols, growth):
    """Estimated work per query (items of W lanes + ranges) at level 0, from a data subsample."""
    rep = grid[0].rep if grid else 1
    if _use_full_scan(grid, 0, growth, n_data * rep):
        return n_data / W + _n_ranges(grid, 0, growth) * _RANGE_COST
    offsets = _offsets(grid, _table(grid, cols_sub)[0])
    items = _stencil_items(grid, offsets, qcols, 0, growth, n_data / cols_sub.shape[1])
    return float((items + _RANGE_COST).sum(axis=1).mean())  # items (the last one of a range partly empty) + plan


def _choose_grid(cols, d_s, kind, d_g, radius_s, radius_g, growth, qcols, col_lo, col_hi):
    """Cheapest grid by :func:`_grid_cost` over axis prefixes (by selectivity), cell widths and
    replication of the first axis."""
    n = cols.shape[1]
    rng = np.random.default_rng(0)  # affects speed only, never results
    sub = cols[:, rng.choice(n, min(n, 1 << 16), replace=False)] if n > (1 << 16) else cols
    qs = qcols[:, rng.choice(qcols.shape[1], min(qcols.shape[1], _SAMPLE), replace=False)]
    # Axes by selectivity: the fraction of the data within one base radius of a query.
    order = _axis_order(_axes_info(d_s, kind, d_g, radius_s, radius_g), sub, qs)
    max_rep = max(1, min(_MAX_REP, _MAX_ENTRIES // max(n, 1)))
    best, best_cost = (), n / W * 1.0
    for axes, widths in _candidate_axes(order):
        plain = _coarsen(axes, widths, col_lo, col_hi, n)
        if plain is None:
            continue
        span0 = plain[0].span(0, growth)
        reps = [1] + ([r for r in {span0, span0 - 1} if 2 <= r <= max_rep and 2 * r <= plain[0].n]
                      if len(axes) >= 2 else [])
        for r in sorted(reps):
            grid = plain if r == 1 else _coarsen(axes, widths, col_lo, col_hi, n, r)
            if grid is None:
                continue
            cost = _grid_cost(grid, sub, n, qs, growth) * (1 + 0.02 * (r - 1))  # + memory
            if cost < best_cost * 0.98:
                best, best_cost = grid, cost
    return best


def _grid_spec(spec, info, max_rep=1):
    """A forced grid: ``(axes of info, widths, replication)`` from ``(axis, width)`` pairs, the
    first optionally ``(axis, width, replication 1..max_rep)`` with at least 2 axes."""
    message = (f"grid must list at most {MAX_GRID_AXES} distinct axes in [0, {len(info)}) as (axis, width) with "
               "finite positive widths" + (f" (the first may add a replication 1..{max_rep}, with at least 2 "
                                           "axes)" if max_rep > 1 else "") + f", got {spec!r}")
    try:
        spec = [tuple(a) for a in spec]
        axes, widths = [a[0] for a in spec], [float(a[1]) for a in spec]
    except (TypeError, ValueError, IndexError) as e:
        raise ValueError(message) from e
    rep = spec[0][2] if spec and len(spec[0]) == 3 else 1
    if (any(isinstance(a, bool) or not isinstance(a, (int, np.integer)) for a in [*axes, rep])
            or len(spec) > MAX_GRID_AXES or not 1 <= rep <= max_rep or (rep > 1 and len(spec) < 2)
            or any(len(a) not in ((2, 3) if j == 0 else (2,)) for j, a in enumerate(spec))
            or len(set(axes)) != len(axes)
            or any(not 0 <= a < len(info) for a in axes) or any(not 0 < w < math.inf for w in widths)):
        raise ValueError(message)
    if axes and info[axes[-1]][2]:
        raise ValueError("the last grid axis must not be the (periodic) angle")
    return [info[a] for a in axes], widths, int(rep)
