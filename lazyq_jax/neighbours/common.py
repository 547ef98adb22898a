"""The core every neighbour search shares (:mod:`~lazyq_jax.neighbours.grid`,
:mod:`~lazyq_jax.neighbours.nd`, :mod:`~lazyq_jax.neighbours.query`): the semantics, the
result type, the float32 membership thresholds and, once a layout has cut each query's
candidate ranges into items of ``W`` entries, everything after it.

Semantics (the reference the tests check against)
-------------------------------------------------
With ``R2S[L] = float32((radius_s * growth**L)**2)``, ``RG[L] = float32(radius_g * growth**L)``
and ``RG2[L] = float32((radius_g * growth**L)**2)`` (each rounded once from float64:
:func:`radius_tables`), a data point ``(s, g)`` belongs to ``B_L(s0, g0)`` iff, computed in
float32 exactly as written (every product and every sum rounded to float32, sums left to
right)::

    ds2 = ((s[0]-s0[0])**2 + (s[1]-s0[1])**2) + ... + (s[d_s-1]-s0[d_s-1])**2
    ds2 < R2S[L]  and  goal_ok

    angle:  d = |wrap(g) - wrap(g0)|;  min(d, TWO_PI - d) < RG[L]
    vector: dg2 = (g[0]-g0[0])**2 + ... + (g[d_g-1]-g0[d_g-1])**2;  dg2 < RG2[L]
    none:   goal_ok = True

``wrap`` is :func:`wrap_angle` (float32 ``PI``/``TWO_PI``): the paper's ``cos(g - g0) >
cos(0.1)`` as a wrapped distance, so ``-pi`` and ``pi`` are neighbours.  ``level`` is the
smallest ``L >= 0`` with ``|B_L| >= k``; ``idx`` holds ``k`` distinct indices drawn
uniformly without replacement from ``B_level``; ``count = |B_level|``.  A float64
evaluation can disagree on pairs within an ulp of a boundary; the float32 formula is the
definition.  XLA on CPU contracts ``a*b + c`` into a fused multiply-add (about a quarter of
random ``x*x + y*y`` differ in the last bit), so every square is ``max(d*d, 0)`` (:func:`_sq`):
the jitted test is bitwise the formula.

After the layout: :func:`_items` (ranges ``[Q, R]`` -> items), :func:`_member_words` (a
32-bit membership word per item and level), :func:`_pick_level` (popcount sums) and
:func:`_sample_members` (``k`` distinct ranks by Floyd's algorithm from a per-query hash,
each mapped to its entry through the prefix of popcounts and a select-in-word)."""

from __future__ import annotations

import contextlib
import math

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

try:  # NumPy's switch for its madvise(MADV_HUGEPAGE) on large arrays (see _without_hugepage_advice)
    from numpy._core.multiarray import _set_madvise_hugepage
except ImportError:  # not every NumPy build has it
    _set_madvise_hugepage = None

PI = np.float32(np.pi)
TWO_PI = np.float32(2 * np.pi)
W = 32  # entries per item (bits per membership word)


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



@contextlib.contextmanager
def _without_hugepage_advice():
    """NumPy's large-array ``madvise(MADV_HUGEPAGE)`` off while a host build (the grid's or the
    general search's) allocates, and restored after.  Where the kernel's transparent huge pages
    have ``defrag = madvise`` (Linux's default), those advised allocations can stall in
    synchronous compaction, most in a process's first builds: at N = 1M on the 2-core CPU the
    grid's build took 0.5-1.8 s in some calls with the advice and 0.26-0.33 s in others, a
    steady 0.27-0.31 s without (``experiments/bench_neighbours.py``; docs/performance.md)."""
    if _set_madvise_hugepage is None:
        yield
        return
    was = _set_madvise_hugepage(False)
    try:
        yield
    finally:
        _set_madvise_hugepage(was)


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


def _level_tables(radius_s, radius_g, growth, levels):
    """float32 ``(R2S, RG, RG2)`` of ``levels``: the state, angle and goal-vector thresholds
    (radii beyond float32 are inf, a fine threshold)."""
    with np.errstate(over="ignore"):
        r2s, rg = radius_tables(radius_s, radius_g, growth, levels)
        rg2, _ = radius_tables(radius_g, radius_g, growth, levels)
    return r2s, rg, rg2


def _pow2(n: int) -> int:
    return 1 << max(int(n) - 1, 0).bit_length()


def _bucket(n: int, coarse: bool = False) -> int:
    """Round ``n`` up to 16 significant levels per power of two (bounds recompiles, <7% waste),
    or to a power of two if ``coarse`` (small later passes: more sharing, more waste)."""
    n = max(int(n), 1)
    unit = 1 << max(n.bit_length() - (1 if coarse else 4), 0)
    return -(-n // unit) * unit


def _levels_to_cover(diags, radii, growth) -> int:
    """A level whose radii cover every (data, query) pair, so ``|B| = N >= k`` there:
    ``diags`` the extents of the blocks (state, goal), ``radii`` their base radii."""
    lg = math.log(growth)
    return 1 + max([0] + [math.ceil(math.log(d / r) / lg) for d, r in zip(diags, radii) if d > 0])



def stable_order(key, upper: int | None = None):
    """``np.argsort(key, kind="stable")`` for integer keys, as an LSD radix sort over 16-bit
    digits (NumPy sorts 16-bit integers by counting): ~10x faster than a comparison sort at
    1M keys (0.01 s against 0.11 s, 2 cores).  ``upper``: the caller knows the keys lie in
    ``[0, upper)``; up to ``2**16`` that is one pass on the keys as they are, without the
    shift by their minimum.  Host only; returns int64 indices."""
    key = np.asarray(key)
    if key.size == 0:
        return np.zeros(0, np.int64)
    if upper is not None and upper <= 1 << 16:
        return np.argsort(key.astype(np.uint16), kind="stable")
    key = key.astype(np.int64) - int(key.min())
    top = int(key.max())
    order = np.argsort((key & 0xFFFF).astype(np.uint16), kind="stable")
    shift = 16
    while top >> shift:
        order = order[np.argsort(((key[order] >> shift) & 0xFFFF).astype(np.uint16), kind="stable")]
        shift += 16
    return order


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



# ----------------------------------------------------------------------------- items


def _cumsum_small(x, b: int = 64):
    """Inclusive cumsum of a 1-D int32 array whose values lie in ``[0, 2**18)`` (popcounts):
    within blocks of ``b`` a float32 product with a triangular matrix (exact: every partial
    sum is below ``2**24``), then ``jnp.cumsum`` of the block totals.  At 8.4M entries on 2
    cores: 0.068 s against 0.106 s for ``jnp.cumsum``, compiling as fast (an associative scan
    runs in 0.057 s but compiles ~1 s longer per use)."""
    n = x.shape[0]
    if n <= 4 * b:
        return jnp.cumsum(x)
    y = jnp.pad(x, (0, -n % b)).reshape(-1, b).astype(jnp.float32)
    tri = jnp.triu(jnp.ones((b, b), jnp.float32))
    within = jnp.dot(y, tri, precision=jax.lax.Precision.HIGHEST).astype(jnp.int32)
    tot = within[:, -1]
    return (within + (jnp.cumsum(tot) - tot)[:, None]).reshape(-1)[:n]


def _items(start, length, n_items: int):
    """Cut every range ``[Q, R]`` into items of ``W`` entries; items grouped by query, in order.

    Returns ``(item_q, item_start, item_valid, first item of each query, items per query)``.
    Items past ``n_items`` are not represented (the caller checks the capacity).
    """
    q, r = start.shape
    nit = ((length + W - 1) // W).reshape(-1)
    cum = jnp.cumsum(nit)
    first = cum - nit
    # pair of item t = (number of pairs starting at or before t) - 1; empty pairs share
    # their start with the next non-empty pair and are counted before it.
    starts = jnp.zeros(n_items, jnp.int32).at[first].add(1, mode="drop")
    pair = jnp.clip(jnp.cumsum(starts) - 1, 0, q * r - 1)
    chunk = jnp.arange(n_items, dtype=jnp.int32) - first[pair]
    item_start = start.reshape(-1)[pair] + W * chunk
    item_valid = jnp.clip(length.reshape(-1)[pair] - W * chunk, 0, W)
    per_query = nit.reshape(q, r)
    return pair // r, item_start, item_valid, first.reshape(q, r)[:, 0], per_query.sum(1)


def _steps(max_items: int) -> int:
    """Static search steps for queries of up to ``max_items`` items: the bit length (exact up
    to 5), else rounded up to a multiple of 4 (fewer recompiles)."""
    b = max(int(max_items).bit_length(), 1)
    return b if b <= 5 else -(-b // 4) * 4


# ----------------------------------------------------------------------------- membership


def _sq(v):
    """``v*v`` rounded to float32 before any add: the ``max`` keeps XLA from contracting it
    with a later add into a fused multiply-add (module docstring)."""
    return jnp.maximum(v * v, jnp.float32(0))


def _member_words(index, qcols, item_q, item_start, item_valid, lo: int, hi: int):
    """Membership words ``[T, hi - lo + 1]`` (bit w: entry ``item_start + w`` is in ``B_level``).

    ``index``: any engine's index with ``cols`` (float32 ``[n_cols, E + W]``: the state
    dimensions, then the wrapped angle or the goal's; ``W`` padding entries at the end),
    ``d_s``, ``goal``, ``d_g``, ``radius_s``, ``radius_g``, ``growth``; ``qcols`` the queries'
    columns ``[n_cols, Q]``.  The test is the float32 formula of the module docstring.
    """
    levels = np.arange(lo, hi + 1)
    r2s, rg, rg2 = _level_tables(index.radius_s, index.radius_g, index.growth, levels)
    lane = jnp.arange(W, dtype=jnp.int32)
    n_cols = index.cols.shape[0]
    # One contiguous [n_cols, W] slice per item (cols carry W padding entries at the end):
    # ~3x faster on CPU than gathering every lane separately.
    start = jnp.clip(item_start, 0, index.cols.shape[1] - W)
    x = jax.vmap(lambda s: jax.lax.dynamic_slice(index.cols, (0, s), (n_cols, W)), out_axes=1)(start)
    qi = qcols[:, item_q]  # [n_cols, T]
    ds2 = None
    for c in range(index.d_s):
        p = _sq(x[c] - qi[c][:, None])
        ds2 = p if ds2 is None else ds2 + p
    dg, tg = None, None
    if index.goal == "angle":
        d = jnp.abs(x[index.d_s] - qi[index.d_s][:, None])
        dg, tg = jnp.minimum(d, TWO_PI - d), rg
    elif index.goal == "vector":
        for c in range(index.d_s, index.d_s + index.d_g):
            p = _sq(x[c] - qi[c][:, None])
            dg = p if dg is None else dg + p
        tg = rg2
    valid = lane < item_valid[:, None]
    bits = jnp.left_shift(jnp.uint32(1), lane.astype(jnp.uint32))
    if len(levels) == 1:
        ok = valid & (ds2 < r2s[0])
        if dg is not None:
            ok = ok & (dg < tg[0])
        return jnp.sum(jnp.where(ok, bits, jnp.uint32(0)), axis=1, dtype=jnp.uint32)[:, None]
    # Several levels: one variadic reduction over the lanes with a word per level, so that XLA
    # fuses the slice gathers and distances into it once (separate reductions per level made it
    # materialise the gathered slices, [n_cols, T, W] floats: ~9x slower).
    words = []
    for li in range(len(levels)):
        ok = valid & (ds2 < r2s[li])
        if dg is not None:
            ok = ok & (dg < tg[li])
        words.append(jnp.where(ok, bits, jnp.uint32(0)))
    zero = [jnp.uint32(0)] * len(words)
    red = jax.lax.reduce(words, zero, lambda a, b: [x | y for x, y in zip(a, b)], (1,))
    return jnp.stack(red, axis=1)


# ----------------------------------------------------------------------------- sampling


def _mulhi32(a, b):
    """High 32 bits of the 64-bit product of two uint32 arrays (no x64 needed)."""
    m16 = jnp.uint32(0xFFFF)
    a0, a1, b0, b1 = a & m16, a >> 16, b & m16, b >> 16
    lo_lo, hi_lo, lo_hi, hi_hi = a0 * b0, a1 * b0, a0 * b1, a1 * b1
    cross = (lo_lo >> 16) + (hi_lo & m16) + lo_hi
    return (hi_lo >> 16) + (cross >> 16) + hi_hi


_UNROLL_QUERIES = 1 << 18  # Floyd unrolled from this many queries (and k <= _UNROLL_K) on
_UNROLL_K = 24  # the static shapes: its compile cost pays only in large, repeated passes


def _floyd_draw(seed, m, k: int, i):
    """Draw ``i`` of Floyd's algorithm before the collision test: ``(j, t ~ U{0..j})``."""
    j = m - k + i
    i = jnp.asarray(i, jnp.uint32)
    u = _mix32(_mix32(seed ^ (i * jnp.uint32(0x9E3779B9))) + i)
    return j, _mulhi32(u, (j + 1).astype(jnp.uint32)).astype(jnp.int32)


def _floyd_ranks(seed, m, k: int):
    """``k`` distinct ranks in ``[0, m)`` per row, uniform over k-subsets (Floyd's algorithm).

    Draw ``t ~ U{0..j}`` is ``mulhi(u, j + 1)`` with ``u`` a 32-bit hash of the query's
    ``seed`` and the draw number (bias below ``(j + 1) / 2**32``); a draw already taken
    becomes ``j``.  Two programs, the same ranks: unrolled (draw ``i`` compares with the
    ``i`` earlier draws only) for large batches and small ``k``, else a ``fori_loop`` over a
    ``[k, Q]`` buffer.  At Q = 1M, k = 20 on 2 cores: unrolled 0.12 s a run but 1.6-2.1 s to
    compile (and minutes at k = 60), the loop 0.21 s and 0.15 s to compile.
    """
    if m.shape[0] >= _UNROLL_QUERIES and k <= _UNROLL_K:
        cols = []
        for i in range(k):
            j, t = _floyd_draw(seed, m, k, i)
            taken = jnp.zeros(m.shape, bool)
            for c in cols:
                taken = taken | (c == t)
            cols.append(jnp.where(taken, j, t))
        return jnp.stack(cols, axis=-1)
    lanes = jnp.arange(k, dtype=jnp.int32)[:, None]

    def draw(i, cols):  # cols [k, Q]: a draw is one contiguous row (2x faster than [Q, k])
        j, t = _floyd_draw(seed, m, k, i)
        taken = jnp.any((cols == t[None, :]) & (lanes < i), axis=0)
        return jax.lax.dynamic_update_index_in_dim(cols, jnp.where(taken, j, t), i, axis=0)

    return jax.lax.fori_loop(0, k, draw, jnp.zeros((k,) + m.shape, jnp.int32)).T


def _key_words(key):
    """Two uint32 words of ``key`` (one threefry call, outside the passes)."""
    return jax.random.bits(key, (2,), jnp.uint32)


def _query_seeds(key_words, q_ids):
    """uint32 per query, a keyed hash of its row ``q``: independent of batching and padding."""
    x = _mix32(q_ids.astype(jnp.uint32) ^ jnp.uint32(0x6A09E667))
    return _mix32(_mix32(x ^ key_words[0]) + key_words[1])


_WINDOW_STEPS = 5  # queries of up to 2**5 items: the window count, else the binary search


def _sample_members(orig, words, li, found, m, seed, item_q, item_start, first, n_q, *, k: int,
                    steps: int):
    """``k`` distinct members of each query's ball, uniform over its k-subsets.

    ``words [T, levels]`` and the items (``item_q``, ``item_start``; ``first``/``n_q``: each
    query's first item and item count) as :func:`_items` / :func:`_member_words` give them;
    ``li``/``found``/``m`` from :func:`_pick_level`; ``seed`` uint32 ``[Q]``; ``steps`` at
    least the bit length of the largest ``n_q`` (:func:`_steps`).  Returns int32
    ``[Q, k]`` rows ``orig[entry]`` (``-1`` where not ``found``).

    The two halves, :func:`_draw_ranks` and :func:`_select_members`, are what the host-driven
    searches run as two programs (see :func:`_draw_ranks`).
    """
    word, prefix, ranks = _draw_ranks(words, li, found, m, seed, item_q, k=k)
    return _select_members(orig, word, prefix, ranks, found, item_start, first, n_q, steps=steps)


def _draw_ranks(words, li, found, m, seed, item_q, *, k: int):
    """The first half of :func:`_sample_members`: each item's word at its query's level, the
    global exclusive prefix of their popcounts, and each query's ``k`` distinct ranks in
    ``[0, m)`` (Floyd).  Returns ``(word [T], prefix [T], ranks [Q, k])``.

    The host-driven searches (:func:`lazyq_jax.neighbours.grid.search_all`) end their program
    here and run :func:`_select_members` as a second one: in one program XLA on the CPU fuses
    ``word`` and ``prefix`` (cheap elementwise maps of the popcount sums) into the later
    per-rank gathers and recomputes them, chains of dependent random gathers, for every rank
    and bit step (~0.2 s of a 1M-query pass on 2 cores; ``lax.optimization_barrier`` does not
    stop it on the CPU).
    """
    # Words of each item at its query's level (one level: no gather), their popcounts and
    # global exclusive prefix.
    word = words[:, 0] if words.shape[1] == 1 else jnp.take_along_axis(words, li[item_q][:, None], 1)[:, 0]
    pc = jax.lax.population_count(word).astype(jnp.int32)
    prefix = _cumsum_small(pc) - pc  # pc <= W
    ranks = _floyd_ranks(seed, jnp.where(found, m, k), k)  # [Q, k]
    return word, prefix, ranks


def _select_members(orig, word, prefix, ranks, found, item_start, first, n_q, *, steps: int):
    """The second half of :func:`_sample_members`: each rank's member, ``orig[entry]``
    (``-1`` where not ``found``)."""
    cap = word.shape[0]
    target = jnp.take(prefix, jnp.minimum(first, cap - 1))[:, None] + ranks
    # The item of each rank: the last item t of the query with prefix[t] <= target.
    if steps <= _WINDOW_STEPS:
        # Up to 32 items a query: count the query's items at or below each rank in a window of
        # its prefixes (one contiguous slice a query; 2x faster on CPU than the binary search
        # at 16 items, equal at 32).
        win = 1 << steps
        big = jnp.iinfo(jnp.int32).max
        padded = jnp.concatenate([prefix, jnp.full((win,), big, jnp.int32)])
        window = jax.vmap(lambda f: jax.lax.dynamic_slice(padded, (f,), (win,)))(jnp.minimum(first, cap))
        window = jnp.where(jnp.arange(win) < n_q[:, None], window, big)  # [Q, win]
        below = jnp.sum((window[:, None, :] <= target[:, :, None]).astype(jnp.int32), axis=2)
        t = jnp.minimum(first[:, None] + jnp.maximum(below - 1, 0), cap - 1)
    else:
        # A binary search in the query's items, unrolled (faster on CPU than a loop).
        lo_t = jnp.broadcast_to(first[:, None], ranks.shape)
        size = jnp.broadcast_to(n_q[:, None], ranks.shape)
        for _ in range(steps):
            half = size // 2
            mid = jnp.minimum(lo_t + half, cap - 1)
            go = (half > 0) & (prefix[mid] <= target)
            lo_t = jnp.where(go, mid, lo_t)
            size = jnp.where(go, size - half, half)
        t = jnp.minimum(lo_t, cap - 1)
    bit = _select_bit(word[t], target - prefix[t])
    idx = orig[jnp.minimum(item_start[t] + bit, orig.shape[0] - 1)]
    return jnp.where(found[:, None], idx, -1)
