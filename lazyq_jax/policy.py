"""The lazy greedy policy, Eq. (9): act along beta of the local fit to the dataset."""

from __future__ import annotations

from functools import partial
from typing import Any, Callable

import jax
import jax.numpy as jnp
from flax import struct

from lazyq_jax.config import GREEDY_ACTIONS, NO_MODEL_ACTIONS
from lazyq_jax.local_model import (boundary_action, epanechnikov_weights, fit_local_linear, greedy_action,
                                   neighbour_offsets)
from lazyq_jax.neighbours.query import PolicyIndex, build_policy_index, query_policy
from lazyq_jax.targets import bootstrap_table, values_at_goals
from lazyq_jax.types import Transitions


@struct.dataclass
class FitKernel:
    """What distance-weighted local fits (``neighbours.fit_weights="epanechnikov"``) read: the
    dataset's points in the search space ``x [N, d]`` and goals, and the radii."""

    x: jax.Array
    goals: jax.Array | None
    radius_s: float = struct.field(pytree_node=False)
    radius_g: float = struct.field(pytree_node=False)
    growth: float = struct.field(pytree_node=False)


@struct.dataclass
class LazyPolicy:
    """Everything the policy reads: a pytree, so it can be passed into ``jit`` (and stacked
    over seeds for ``vmap``)."""

    index: PolicyIndex  # the bounded per-step neighbour query (lazyq_jax.neighbours.query)
    actions: jax.Array  # [N, n_a] the dataset's actions a_j
    values: jax.Array  # [N] y_j = r_j + gamma (1 - done_j) V(s'_j, g_j), from the trained V
    action_length: jax.Array  # c (a float32 scalar)
    action_set: str = struct.field(pytree_node=False, default="ball")
    features: Callable | None = struct.field(pytree_node=False, default=None)  # phi(s): the search space
    states: jax.Array | None = None  # [N, d_s] the dataset's states, for state-offset local models
    goals: jax.Array | None = None  # the dataset's goals, for goal-offset local models
    kernel: FitKernel | None = None  # distance-weighted local fits (None: the paper's least squares)
    # where the local model prefers no action: "zero" or "random" (NeighbourConfig.no_model_action)
    no_model_action: str = struct.field(pytree_node=False, default="zero")
    # train.bootstrap_goal="row": the neighbours' next states [N, d_s], valued every step at the
    # query's goal by value_apply(value_vars, s', g) (the trained V); `values` is then unused
    next_states: jax.Array | None = None
    value_vars: Any = None
    value_apply: Callable | None = struct.field(pytree_node=False, default=None)
    # neighbours.subgoal_steps = H > 0: the two-level step (lazy_subgoals), which reads the
    # rows' trajectories (traj_last [N]: the row of each row's trajectory's last transition)
    # and values the neighbours per step, as with bootstrap_goal="row"
    subgoal_steps: int = struct.field(pytree_node=False, default=0)
    traj_last: jax.Array | None = None
    # psi(g): where the query's goal is compared with the index's goals (Problem.goal_features;
    # the index and the kernel then hold psi of the dataset's goals)
    goal_features: Callable | None = struct.field(pytree_node=False, default=None)
    # Eq. (9)'s argmax over the action "set" or over the neighbourhood's actions ("data")
    greedy: str = struct.field(pytree_node=False, default="set")
    # neighbours.far_subgoal_steps = F > 0: a far subgoal F steps ahead before the near one
    far_subgoal_steps: int = struct.field(pytree_node=False, default=0)


def policy_index(data_s, data_g, *, k: int, radius_s: float, radius_g: float, growth: float,
                 max_level: int, n_valid: int | None = None) -> PolicyIndex:
    """The policy's neighbour index over a dataset whose rows ``>= n_valid`` are padding: the
    bounded per-step query of :func:`lazyq_jax.neighbours.query.build_policy_index`, in every
    space (the paper's 2-D states with angle goals included: there it is 3.8x faster than
    the grid's ``query_neighbours``, whose static window is ``max_level``'s stencil for every
    query; docs/performance.md)."""
    return build_policy_index(data_s, data_g, k=k, radius_s=radius_s, radius_g=radius_g,
                              growth=growth, max_level=max_level, n_valid=n_valid)


def make_lazy_policy(value_fn: Callable, data: Transitions, *, gamma: float, action_length: float,
                     action_set: str = "ball", k: int = 20, radius_s: float = 0.06,
                     radius_g: float = 0.1, growth: float = 2 ** (1 / 3), max_level: int = 8,
                     no_model_action: str = "zero", greedy: str = "set") -> LazyPolicy:
    """Precompute what the policy needs from a trained ``value_fn(s, g)`` and its dataset.

    The neighbourhood semantics are those of training (§V-A-2); ``max_level`` bounds
    the growths a policy query may use, ``no_model_action`` what a step does where the
    local model prefers no action and ``greedy`` where Eq. (9) maximises (see
    :func:`lazy_policy`).  Any space: states
    ``[N, d_s]``, goals ``[N]`` (angles), ``[N, d_g]`` or ``None``; the index is the bounded
    per-step query of :mod:`lazyq_jax.neighbours.query`.
    """
    index = policy_index(data.s, data.g, k=k, radius_s=radius_s, radius_g=radius_g, growth=growth,
                         max_level=max_level)
    values = jax.jit(bootstrap_table, static_argnums=(0,))(value_fn, data, gamma)
    if no_model_action not in NO_MODEL_ACTIONS:
        raise ValueError(f"no_model_action must be one of {NO_MODEL_ACTIONS}, got {no_model_action!r}")
    if greedy not in GREEDY_ACTIONS:
        raise ValueError(f"greedy must be one of {GREEDY_ACTIONS}, got {greedy!r}")
    return LazyPolicy(index, data.a, values, jnp.float32(action_length), action_set,
                      no_model_action=no_model_action, greedy=greedy)


def neighbour_values(policy: LazyPolicy, rows: jax.Array, g) -> jax.Array:
    """The values ``[B, k]`` the local fit of the queries' neighbourhoods ``rows [B, k]``
    regresses: the table ``y_j = r_j + gamma (1 - done_j) V(s'_j, g_j)``, or with
    ``train.bootstrap_goal="row"`` ``V(s'_j, g)`` at the query's goal ``g`` (the query's own
    reward and discount are the same for every neighbour and do not change ``beta``)."""
    if policy.value_apply is None:
        return policy.values[rows]
    return values_at_goals(partial(policy.value_apply, policy.value_vars), policy.next_states[rows], g)


def lazy_subgoals(policy: LazyPolicy, rows: jax.Array, valid: jax.Array, s: jax.Array,
                  g: jax.Array, steps: int | None = None) -> jax.Array:
    """The subgoals ``w [B, d_s]`` of the two-level step (``neighbours.subgoal_steps = H >
    0``): HIQL's hierarchy (Park et al., 2023) made lazy, with no subgoal network, the
    subgoals being the data's own states.

    Each neighbour ``j`` of the query's neighbourhood ``rows [B, k]`` (``valid``: found)
    offers the state its trajectory reached ``H`` steps later, ``w_j = s'[min(j + H - 1,
    last_j)]`` (the trajectory's final state where it ends sooner); the subgoal is the
    candidate of the largest ``V(w_j, g)``, or the goal ``g`` itself once it is as near as
    the candidates lead, ``V(s, g) >= mean_j V(s, w_j)`` (one V measures both, whatever the
    reward's scale; switching where no candidate is valued above ``s`` instead stops at V's
    local maxima, the walls that the subgoals are there to go round).  The low level is then
    Eq. (9)'s step with the neighbours valued at ``w`` instead of ``g``: the greedy step
    compares values one step apart, where a learned V's errors are as large as its
    differences; the subgoal compares values ``H`` steps apart.  Where the query has no
    neighbourhood (``valid`` all false) ``w`` is meaningless and the step is the zero action.
    ``steps``: ``H`` (default ``policy.subgoal_steps``; the far level's ``far_subgoal_steps``).
    """
    v = partial(policy.value_apply, policy.value_vars)
    steps = policy.subgoal_steps if steps is None else steps
    ahead = policy.next_states[jnp.minimum(rows + steps - 1, policy.traj_last[rows])]
    v_ahead = jnp.where(valid, values_at_goals(v, ahead, g), -jnp.inf)
    best = jnp.argmax(v_ahead, axis=1)
    w = jnp.take_along_axis(ahead, best[:, None, None], axis=1)[:, 0]
    b, k, d = ahead.shape
    v_reach = v(jnp.broadcast_to(s[:, None], ahead.shape).reshape(b * k, d), ahead.reshape(b * k, d))
    reach = jnp.sum(jnp.where(valid, v_reach.reshape(b, k), 0.0), axis=1) / jnp.maximum(
        jnp.sum(valid, axis=1), 1)
    at_goal = v(s, g) >= reach
    return jnp.where(at_goal[:, None], g, w)


def in_sample_greedy(actions: jax.Array, valid: jax.Array, beta: jax.Array) -> jax.Array:
    """Eq. (9) restricted to the neighbourhood: the action ``a_j [B, n_a]`` of the largest
    ``beta . a_j`` among the valid neighbours ``actions [B, k, n_a]`` (``neighbours.greedy=
    "data"``); zero where ``beta = 0`` (every action equally good: no preference)."""
    score = jnp.where(valid, jnp.einsum("bkn,bn->bk", actions, beta), -jnp.inf)
    best = jnp.take_along_axis(actions, jnp.argmax(score, axis=-1)[:, None, None], axis=1)[:, 0]
    return jnp.where(jnp.any(beta != 0, axis=-1, keepdims=True), best, 0.0)


def lazy_policy(policy: LazyPolicy, key: jax.Array, s: jax.Array, g: jax.Array):
    """Greedy actions (Eq. 9) for a batch of states ``s[B, d_s]``, goals ``g[B]`` /
    ``g[B, d_g]`` / ``None`` (as the dataset's).

    For each query: its neighbourhood in the dataset (distances between ``policy.features``
    of the states and ``policy.goal_features`` of the goals, where the policy has them), the
    local fit
    ``y_j ~ alpha + beta.a_j`` (Eq. 5-6; weighted by distance with a ``policy.kernel``), and
    the maximiser of ``beta . a`` over the
    action set (:func:`lazyq_jax.local_model.greedy_action`), or with ``policy.greedy ==
    "data"`` over the neighbourhood's actions (:func:`in_sample_greedy`).  Pure and jittable (use
    it inside ``lax.scan`` rollouts).  A query with no neighbourhood within
    ``max_level`` growths (far outside the data) has ``found = False``.  Where the model prefers no action (no neighbourhood, or ``beta = 0``: every neighbour
    took the same action) the action is zero, or with ``policy.no_model_action ==
    "random"`` a random action of the set's boundary
    (:func:`lazyq_jax.local_model.boundary_action`) drawn from ``fold_in(key, 1)``: the
    neighbour query keeps ``key``, so every other step is the same in both modes.

    With ``policy.subgoal_steps > 0`` the step is the low level of a two-level policy: its
    neighbours are valued at a subgoal among the data (:func:`lazy_subgoals`), not at ``g``;
    with ``policy.far_subgoal_steps > 0`` that subgoal is chosen towards a far one.

    Returns ``(actions[B, n_a], beta[B, n_a], found[B])``.
    """
    x = s if policy.features is None else policy.features(s)
    gq = g if policy.goal_features is None or g is None else policy.goal_features(g)
    nb = query_policy(policy.index, key, x, None if policy.value_apply is not None else gq)
    rows = jnp.maximum(nb.idx, 0)
    if policy.subgoal_steps > 0:
        if policy.far_subgoal_steps > 0:  # three levels: the near subgoal heads for a far one
            g = lazy_subgoals(policy, rows, nb.idx >= 0, s, g, policy.far_subgoal_steps)
        g = lazy_subgoals(policy, rows, nb.idx >= 0, s, g)
    offsets = None if policy.states is None else neighbour_offsets(
        policy.states[rows], s, None if policy.goals is None else policy.goals[rows],
        None if policy.goals is None else g)
    weights = None
    if policy.kernel is not None:
        kn = policy.kernel
        weights = epanechnikov_weights(kn.x[rows], x, None if kn.goals is None else kn.goals[rows],
                                       None if kn.goals is None else gq, nb.level,
                                       radius_s=kn.radius_s, radius_g=kn.radius_g, growth=kn.growth)
    _, beta = fit_local_linear(policy.actions[rows], neighbour_values(policy, rows, g), weights,
                               offsets=offsets)
    found = nb.level >= 0
    if policy.greedy == "data":
        step = in_sample_greedy(policy.actions[rows], nb.idx >= 0, beta)
    else:
        step = greedy_action(beta, policy.action_length, policy.action_set)
    action = jnp.where(found[:, None], step, 0.0)
    if policy.no_model_action == "random":
        undecided = jnp.all(action == 0, axis=-1)
        draw = boundary_action(jax.random.fold_in(key, 1), action.shape, policy.action_length,
                               policy.action_set)
        action = jnp.where(undecided[:, None], draw, action)
    return action, beta, found
