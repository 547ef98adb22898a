"""Bellman targets of the lazy model (paper Eq. 7-8, 11-14).

The action set is the ball of radius ``c`` (``action_length``; ``action_set="ball"``, the
paper's), so ``max_{|a|<=c} beta^T a = c ||beta||`` (Eq. 7), attained at
``c beta/||beta||`` (Eq. 9); or the box ``|a_i| <= c`` (``"box"``), where the maximum is
``c sum_i |beta_i|`` at ``c sign(beta)``.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
from flax import struct
from jax.sharding import Mesh

from lazyq_jax.local_model import (apply_projection, expectile, fit_local_linear, fit_with_offsets,
                                   greedy_action, max_linear, neighbour_offsets,
                                   precompute_projection, safe_norm)
from lazyq_jax.parallel import constrain, mesh_size, replicated, sharded
from lazyq_jax.types import Transitions

ValueFn = Callable[[jax.Array, jax.Array], jax.Array]  # (s [B, d_s], g [B] | [B, d_g] | None) -> V [B]


def lazy_target(alpha, beta, values, action_length, clip=True, action_set="ball", actions=None):
    """``V(s, g)`` of the lazy model: Eq. (7) ``alpha + max_a beta.a`` (``c ||beta||`` on the
    ball; ``clip=False``) or Eq. (8) ``min(alpha + max_a beta.a, max_j values_j)``
    (``clip=True``).  With the neighbours' ``actions [..., k, n_a]`` the maximum is over
    them instead of the action set: ``alpha + max_j beta . a_j`` (``target_max="data"``).

    Returns ``(target [...], clip_active [...] bool)``; ``clip_active`` marks where the
    max-bound of Eq. (8) was the smaller term (always false when ``clip=False``).
    """
    if actions is None:
        linear = alpha + max_linear(beta, action_length, action_set)
    else:
        linear = alpha + jnp.max(jnp.einsum("...ka,...a->...k", actions, beta), axis=-1)
    return _clip(linear, values, clip)


def in_sample_target(moved, tau: float, weights=None):
    """``target_max="expectile"``: the ``tau``-expectile of the neighbours' values moved to the
    centre (``moved [..., k]``, :func:`local_fits` with ``in_sample=True``), weighted by the
    fit's ``weights [..., k]`` if any, instead of Eq. (7)'s maximum of the fit over the
    action set.  An in-sample soft maximum over the neighbourhood's own actions with their
    residuals, as IQL's and GCIVL's expectile over the data's next states (Kostrikov et al.
    2022; Park et al. 2024); it never exceeds the largest moved value, so Eq. (8)'s clip has
    nothing to do.  Without offsets (``local_model="action"``) it is 1-Lipschitz in the
    values: with ``gamma < 1`` a contraction.

    Returns ``(target [...], clip_active [...] bool, all false)``.
    """
    target = expectile(moved, tau, weights)
    return target, jnp.zeros(target.shape, bool)


def double_dqn_target(alpha, beta, beta_online, values, action_length, clip=True, action_set="ball"):
    """Eq. (13)-(14): the action ``a_opt = c beta_online / ||beta_online||`` chosen by the
    online network's fit, valued by the target network's fit ``alpha + beta . a_opt``,
    clipped (``clip=True``) by the largest target-network neighbour value.

    Returns ``(target [...], clip_active [...] bool)``.
    """
    linear = alpha + jnp.sum(beta * greedy_action(beta_online, action_length, action_set), axis=-1)
    return _clip(linear, values, clip)


def _clip(linear, values, clip):
    if not clip:
        return linear, jnp.zeros(linear.shape, bool)
    bound = jnp.max(values, axis=-1)
    return jnp.minimum(linear, bound), linear > bound


def bootstrap_values(r, done, v_next, gamma):
    """``y_j = r_j + gamma (1 - done_j) V(s'_j, g_j)`` (the bracket of Eq. 6); terminal
    transitions are not bootstrapped."""
    return r + gamma * jnp.where(done, 0.0, v_next)


def multi_step_transitions(data: Transitions, steps: int, gamma: float
                           ) -> tuple[Transitions, jax.Array]:
    """Each row's ``h``-step transition along its own trajectory (``train.target_steps = H``):
    ``(data with s_next and r replaced, discount [N])`` such that Eq. (6)'s bracket
    ``r + discount (1 - done) V(s', g)`` is the row's ``h``-step return at its own goal,
    ``sum_{t<h} gamma^t r + gamma^h V(s_{j+h}, g_j)``, the n-step return of Watkins (1989)
    and Sutton & Barto (2018, §7.1) with the data's own later actions.

    ``h = min(H, steps to the trajectory's last next state, steps to the goal)``: the path
    stops where its state equals the row's goal (the relabelled goal-reaching rule of
    OGBench, ``success = (goal index == row)``: that row is the terminal success) and where
    the trajectory ends (``Transitions.traj_last``).  The reward is the row's own, the same
    every step until the goal (OGBench's ``r = success - 1``): ``r (1 - gamma^h) / (1 -
    gamma)``.  Terminal rows (``done``) keep ``r`` and ``s_next``.  Rows past a padded
    dataset's end (``traj_last`` 0) get ``h = 1`` and their own ``s_next``.  ``steps = 1`` is
    the data as they are with the scalar ``gamma``.  Traceable; the caller checks the data
    (:meth:`lazyq_jax.agents.lazy.LazyAgent.check_target_steps`).
    """
    if steps == 1:  # the paper's program, unchanged
        return data, gamma
    rows = jnp.arange(data.r.shape[0], dtype=jnp.int32)
    s_next, r, discount = multi_step_rows(data, rows, data.g, data.r, data.done, steps, gamma)
    return data.replace(s_next=s_next, r=r), discount


def multi_step_rows(data: Transitions, rows: jax.Array, g: jax.Array, r: jax.Array,
                    done: jax.Array, steps: int, gamma: float
                    ) -> tuple[jax.Array, jax.Array, jax.Array]:
    """:func:`multi_step_transitions` for the rows ``rows [B]`` of ``data`` with the goals
    ``g [B, d_s]``, rewards ``r [B]`` and ``done [B]`` given (a goal-conditioned agent's fresh
    goals): ``(s_next [B, d_s], r [B], discount [B])`` of each row's path, ``h <= steps``
    steps along its trajectory, stopped at a state equal to its goal or the trajectory's
    end."""
    if data.traj_last is None or g is None or g.ndim != 2:
        raise ValueError("multi-step targets need trajectory data with state goals "
                         "(Transitions.traj_last and g [N, d_s])")
    last = data.traj_last[rows]

    def step(carry, t):  # the path's t-th next state, t = 1..steps
        h, stopped = carry
        at = rows + t - 1
        x = data.s_next[jnp.minimum(at, last)]
        stop = ~stopped & ((at >= last) | jnp.all(x == g, axis=-1))
        return (jnp.where(stop, t, h), stopped | stop), None

    init = (jnp.full(rows.shape, steps, jnp.int32), jnp.zeros(rows.shape, bool))
    (h, _), _ = jax.lax.scan(step, init, jnp.arange(1, steps + 1, dtype=jnp.int32))
    gamma = jnp.float32(gamma)  # so that h = 1 gives the one-step r and gamma bit for bit
    discount = gamma ** h.astype(jnp.float32)
    s_next = jnp.where(done[:, None], data.s_next[rows], data.s_next[rows + h - 1])
    r = jnp.where(done, r, r * ((1.0 - discount) / (1.0 - gamma)))
    return s_next, r, jnp.where(done, gamma, discount)


@struct.dataclass
class TargetDiagnostics:
    """Per-transition diagnostics of :func:`dataset_targets`."""

    clip_active: jax.Array  # bool [N]: the max-bound of Eq. (8)/(11)/(13) was active
    alpha: jax.Array  # [N] target-network alpha
    beta_norm: jax.Array  # [N] target-network ||beta||

    @property
    def clip_fraction(self) -> jax.Array:
        return jnp.mean(self.clip_active.astype(jnp.float32))


def map_rows(f: Callable, n: int, batch_size: int, mesh: Mesh | None = None):
    """``f(rows)`` for ``rows = arange(n)`` in chunks of ``batch_size`` rows (``lax.map``), so
    that memory is bounded by a chunk, not by ``n``.

    ``f`` maps int rows ``[B]`` to a pytree of ``[B, ...]`` arrays; the result is that pytree
    for all ``n`` rows, ``[n, ...]``.  With a ``mesh`` every chunk is split over its devices
    (``batch_size`` is rounded up to a multiple of the device count) and the result is
    replicated.  The last chunk is filled up with rows from the start (``rows % n``), whose
    results are dropped.
    """
    if batch_size <= 0:
        raise ValueError(f"batch_size must be positive, got {batch_size}")
    if n <= 0:
        raise ValueError(f"no rows to map over (n = {n})")
    d = mesh_size(mesh)
    size = -(-min(batch_size, n) // d) * d
    n_b = -(-n // size)
    rows = (jnp.arange(n_b * size, dtype=jnp.int32) % n).reshape(n_b, size)
    chunk = sharded(mesh)
    out = jax.lax.map(lambda r: constrain(f(constrain(r, chunk)), chunk), rows)
    out = jax.tree.map(lambda x: x.reshape(n_b * size, *x.shape[2:])[:n], out)
    return constrain(out, replicated(mesh))


def evaluate_in_batches(v: ValueFn, s, g, batch_size: int, mesh: Mesh | None = None):
    """``v(s, g)`` over ``N`` points in chunks of ``batch_size`` (:func:`map_rows`) to bound
    memory; with a ``mesh`` every chunk is split over its devices and the result is
    replicated."""
    return map_rows(lambda r: v(s[r], None if g is None else g[r]), s.shape[0], batch_size, mesh)


def fit_projection(data: Transitions, neighbours_idx, *, state_offsets: bool = False,
                   goal_offsets: bool = False, weights=None, batch_size: int = 65536,
                   mesh: Mesh | None = None) -> jax.Array:
    """``P [N, 1 + n_a, k]`` with ``(alpha, beta) = P_i @ y[neighbours_idx[i]]``: the part of
    :func:`local_fits`' least squares (Eq. 5-6) that depends on the data alone (the
    neighbours' actions, their state and goal offsets with ``state_offsets`` and
    ``goal_offsets``, the ``weights``), computed once for a set of neighbourhoods so that a
    cycle's fits are one gather and one ``[1 + n_a, k]`` product a row
    (:func:`lazyq_jax.local_model.precompute_projection` of the covariates; the offsets'
    coefficients are dropped: only ``alpha`` and ``beta`` enter Eq. 7).  Equal to the direct
    fit up to float32 rounding (the same centred, ridge-regularised normal equations; the
    direct fit also centres the values ``y``, ``P @ y`` does not, so its rounding grows with
    ``|mean y|`` against their spread: measured unchanged at values near -200, twice the
    error at -2000).  Memory: ``4 (1 + n_a) k`` bytes a row (240 MB for
    1M rows, ``k = 20``, ``n_a = 2``)."""
    idx = jnp.asarray(neighbours_idx)
    n_a = data.a.shape[-1]
    g = data.g if state_offsets and goal_offsets else None
    if weights is not None:
        weights = jnp.asarray(weights, jnp.float32)

    def project(rows):
        nb = idx[rows]
        x = jnp.asarray(data.a[nb], jnp.float32)
        if state_offsets:
            offsets = neighbour_offsets(data.s[nb], data.s[rows], None if g is None else g[nb],
                                        None if g is None else g[rows])
            x = jnp.concatenate([x, jnp.asarray(offsets, jnp.float32)], -1)
        p = precompute_projection(x, None if weights is None else weights[rows])
        return p[:, :1 + n_a]

    return map_rows(project, idx.shape[0], batch_size, mesh)


def dataset_targets(v_target: ValueFn, data: Transitions, neighbours_idx, *, gamma, action_length,
                    clip=True, v_online: ValueFn | None = None, projection=None, batch_size=65536,
                    mesh: Mesh | None = None, action_set: str = "ball"):
    """Targets ``Y [N]`` for the whole dataset and their :class:`TargetDiagnostics`.

    * DQN form (``v_online is None``), Eq. (11)-(12): ``alpha, beta`` fitted to
      ``y = r + gamma (1-done) V_target(s', g)`` over each neighbourhood;
      ``Y = min(alpha + c ||beta||, max_j y_j)`` (no ``min`` if ``clip=False``).
    * Double-DQN form (``v_online`` given), Eq. (13)-(14): ``a_opt = c beta_o/||beta_o||``
      from the fit to ``y`` computed with ``v_online``;
      ``Y = min(alpha_t + beta_t . a_opt, max_j y_t_j)``.

    ``neighbours_idx``: int ``[N, k]`` (``find_neighbours(...).idx`` with the data as
    queries). ``projection``: optional ``precompute_projection(data.a[neighbours_idx])``
    (data-only, reusable every cycle); otherwise the fit is recomputed. ``v_*`` are
    callables ``(s [B, d_s], g) -> V [B]``, e.g. ``functools.partial(net.apply, params)``,
    evaluated in chunks of ``batch_size``. Traceable: wrap the caller in ``jax.jit``.
    ``mesh``: split the work over its devices (see :func:`local_fits`).
    """
    idx = jnp.asarray(neighbours_idx)
    if idx.ndim != 2 or idx.shape[0] != data.r.shape[0]:
        raise ValueError(f"neighbours_idx must be [N={data.r.shape[0]}, k], got {idx.shape}")

    def fit(v):
        return local_fits(v, data, idx, gamma=gamma, projection=projection, batch_size=batch_size,
                          mesh=mesh)

    alpha, beta, y_nb = fit(v_target)
    if v_online is None:
        target, active = lazy_target(alpha, beta, y_nb, action_length, clip, action_set)
    else:
        _, beta_o, _ = fit(v_online)
        target, active = double_dqn_target(alpha, beta, beta_o, y_nb, action_length, clip, action_set)
    return target, TargetDiagnostics(clip_active=active, alpha=alpha, beta_norm=safe_norm(beta))


def bootstrap_table(v: ValueFn, data: Transitions, gamma, batch_size=65536,
                    mesh: Mesh | None = None):
    """``y_j = r_j + gamma (1 - done_j) v(s'_j, g_j)`` for every transition (Eq. 6's bracket),
    with ``v`` evaluated in chunks of ``batch_size`` (split over ``mesh``)."""
    v_next = evaluate_in_batches(v, data.s_next, data.g, batch_size, mesh)
    return bootstrap_values(data.r, data.done, v_next, gamma)


def values_at_goals(v: ValueFn, s_nb, g):
    """``V(s_nb[b, j], g[b])`` ``[B, k]``: every neighbour's state ``s_nb [B, k, d_s]`` valued
    at its centre's goal ``g`` (``[B]`` angles, ``[B, d_g]`` or None), in one call of ``v``."""
    shape = s_nb.shape[:2]
    gg = None if g is None else jnp.broadcast_to(g[:, None], shape + g.shape[1:]).reshape(-1, *g.shape[1:])
    return v(s_nb.reshape(-1, s_nb.shape[-1]), gg).reshape(shape)


def row_goal_values(v: ValueFn, data: Transitions, rows, nb, gamma):
    """``y [B, k]`` with ``train.bootstrap_goal="row"``: each neighbour's next state valued at
    the row's goal with the row's reward, ``y_ij = r_i + gamma (1 - done_i) V(s'_j, g_i)`` for
    the rows ``rows [B]`` and their neighbours ``nb [B, k]`` (Eq. 6's bracket where the reward
    and termination depend on the state and goal alone)."""
    v_next = values_at_goals(v, data.s_next[nb], None if data.g is None else data.g[rows])
    return bootstrap_values(data.r[rows][:, None], data.done[rows][:, None], v_next, gamma)


def local_fits(v: ValueFn, data: Transitions, neighbours_idx, *, gamma, projection=None,
               batch_size=65536, mesh: Mesh | None = None, state_offsets: bool = False,
               goal_offsets: bool = False, weights=None, in_sample: bool = False,
               row_goal: bool = False):
    """``(alpha [N], beta [N, n_a], y_nb [N, k])``: Eq. (5)-(6) for every transition's
    neighbourhood with ``y = r + gamma (1 - done) v(s', g)``; ``y_nb = y[neighbours_idx]``
    (``in_sample=True``: instead each neighbour's value moved to the row's state and goal by
    the fit's offset coefficients, :func:`lazyq_jax.local_model.fit_with_offsets`).
    ``state_offsets``: fit ``alpha + beta . a + gamma' . (s_j - s_i)`` instead
    (:func:`lazyq_jax.local_model.fit_local_linear`'s ``offsets``); ``goal_offsets`` (with
    ``state_offsets``): also ``g_j - g_i`` (:func:`lazyq_jax.local_model.neighbour_offsets`).
    ``weights [N, k]``: weighted least squares (e.g.
    :func:`lazyq_jax.local_model.epanechnikov_weights`); not with a ``projection``.
    ``projection``: :func:`fit_projection` of these neighbourhoods (with the same offsets and
    weights; then ``weights`` is None): ``alpha, beta`` from it instead of solving again
    (not with ``in_sample``, which needs the offsets' coefficients).
    ``row_goal`` (``train.bootstrap_goal="row"``): ``y`` of each neighbourhood at the row's
    goal and with the row's reward (:func:`row_goal_values`: ``k`` evaluations of ``v`` a
    row, in chunks of ``batch_size // k`` rows), not the table of Eq. (6) at the
    neighbours' own goals; not with goal offsets (the goal is the row's for every neighbour).

    The fits run in chunks of ``batch_size`` rows (:func:`map_rows`): the neighbourhoods'
    ``[B, k, ...]`` arrays exist for one chunk at a time, so memory grows with ``N`` only
    by the ``[N, k]`` outputs.  With a ``mesh`` the value table is computed split over the
    devices and then replicated, every chunk of fits is split over the devices, and the
    outputs are replicated.
    """
    idx = jnp.asarray(neighbours_idx)
    if weights is not None and projection is not None:
        raise ValueError("local_fits takes weights or a projection (the weights go into "
                         "fit_projection), not both")
    if projection is not None and in_sample:
        raise ValueError("in_sample moves each neighbour by the offset coefficients, which a "
                         "projection of alpha and beta does not hold: pass projection=None")
    if row_goal and goal_offsets:
        raise ValueError("row_goal values every neighbour at the row's goal: there are no goal "
                         "offsets to fit (use local_model 'action+state')")
    if weights is not None:
        weights = jnp.asarray(weights, jnp.float32)
    y = None if row_goal else bootstrap_table(v, data, gamma, batch_size, mesh)
    g = data.g if state_offsets and goal_offsets else None

    def fit(rows):  # the fits of one chunk of rows: [B, k, ...] arrays live only here
        nb = idx[rows]
        y_nb = row_goal_values(v, data, rows, nb, gamma) if row_goal else y[nb]
        if projection is not None:  # Eq. (5)-(6) fitted once a neighbourhood set: P @ y
            alpha, beta = apply_projection(projection[rows], y_nb)
            return alpha, beta, y_nb
        w = None if weights is None else weights[rows]
        if state_offsets:
            offsets = neighbour_offsets(data.s[nb], data.s[rows], None if g is None else g[nb],
                                        None if g is None else g[rows])
            alpha, beta, moved = fit_with_offsets(data.a[nb], y_nb, w, offsets)
            return alpha, beta, moved if in_sample else y_nb
        alpha, beta = fit_local_linear(data.a[nb], y_nb, w)
        return alpha, beta, y_nb

    rows_a_chunk = max(1, batch_size // idx.shape[1]) if row_goal else batch_size
    return map_rows(fit, idx.shape[0], rows_a_chunk, mesh)
