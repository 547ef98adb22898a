"""The lazy greedy policy, Eq. (9): act along beta of the local fit to the dataset."""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from lazyq_jax.local_model import fit_local_linear, greedy_action
from lazyq_jax.neighbours import GridIndex, build_index, query_neighbours
from lazyq_jax.neighbours.query import ScanIndex, build_scan_index, query_neighbours_scan
from lazyq_jax.targets import bootstrap_table
from lazyq_jax.types import Transitions


class LazyPolicy(NamedTuple):
    """Everything the policy reads: a pytree, so it can be passed into ``jit``."""

    index: GridIndex | ScanIndex  # the push task's grid (2-D states, angle goals), else a scan
    actions: jax.Array  # [N, n_a] the dataset's actions a_j
    values: jax.Array  # [N] y_j = r_j + gamma (1 - done_j) V(s'_j, g_j), from the trained V
    action_length: float


def make_lazy_policy(value_fn: Callable, data: Transitions, *, gamma: float, action_length: float,
                     k: int = 20, radius_s: float = 0.06, radius_g: float = 0.1,
                     growth: float = 2 ** (1 / 3), max_level: int = 8,
                     bounds: tuple[float, float, float, float] | None = None) -> LazyPolicy:
    """Precompute what the policy needs from a trained ``value_fn(s, g)`` and its dataset.

    The neighbourhood semantics are those of training (§V-A-2); ``max_level`` bounds
    the growths a policy query may use (see :func:`lazy_policy`); ``bounds``: the
    grid's bounds (see :func:`lazyq_jax.build_index`; default: the data's).  States
    ``[N, 2]`` with angle goals ``[N]`` get the grid index; any other space
    (``[N, d_s]``, goals ``[N, d_g]`` or ``None``) a scan of the data per query
    (:mod:`lazyq_jax.neighbours.query`).
    """
    if np.ndim(data.s) == 2 and np.shape(data.s)[1] == 2 and data.g is not None and np.ndim(data.g) == 1:
        index = build_index(data.s, data.g, k=k, radius_s=radius_s, radius_g=radius_g, growth=growth,
                            max_level=max_level, bounds=bounds)
    else:
        index = build_scan_index(data.s, data.g, k=k, radius_s=radius_s, radius_g=radius_g, growth=growth,
                                 max_level=max_level)
    values = jax.jit(bootstrap_table, static_argnums=(0,))(value_fn, data, gamma)
    return LazyPolicy(index, data.a, values, float(action_length))


def lazy_policy(policy: LazyPolicy, key: jax.Array, s: jax.Array, g: jax.Array):
    """Greedy actions ``a = c beta / |beta|`` (Eq. 9) for a batch of states ``s[B, d_s]``, goals
    ``g[B]`` / ``g[B, d_g]`` / ``None`` (as the dataset's).

    For each query: its neighbourhood in the dataset, the local fit
    ``y_j ~ alpha + beta.a_j`` (Eq. 5-6), and the action of length ``c`` along beta.
    Pure and jittable (use it inside ``lax.scan`` rollouts).  A query with no
    neighbourhood within ``max_level`` growths (far outside the data) gets the zero
    action and ``found = False``.

    Returns ``(actions[B, n_a], beta[B, n_a], found[B])``.
    """
    if isinstance(policy.index, ScanIndex):
        nb = query_neighbours_scan(policy.index, key, s, g)
    else:
        nb = query_neighbours(policy.index, key, s, g)
    rows = jnp.maximum(nb.idx, 0)
    _, beta = fit_local_linear(policy.actions[rows], policy.values[rows])
    action = greedy_action(beta, policy.action_length)
    found = nb.level >= 0
    return jnp.where(found[:, None], action, 0.0), beta, found
