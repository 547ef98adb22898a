"""OGBench's goal sampling for goal-conditioned agents, in JAX (Park et al. 2024,
``impls/utils/datasets.py: GCDataset.sample`` and ``sample_goals``).

For a minibatch of rows ``idx`` of trajectory data (``Transitions.traj_last``: the row of
each row's trajectory's last transition), a goal index per row:

* with ``p_cur`` the row itself (its own state: a success);
* else with ``p_traj / (1 - p_cur)`` a later row of the same trajectory: at a geometric
  offset ``Geom(1 - discount)`` (``>= 1``) clipped to the trajectory's last row
  (``geom=True``), or uniformly between the next row and the last
  (``round(min(idx + 1, last) d + last (1 - d))``, ``d ~ U[0, 1)``);
* else a uniformly random row.

The goal is that row's state; ``success = (goal index == idx)``, ``r = success - 1``,
``done = success`` (OGBench's ``gc_negative``; ``masks = 1 - success``).  OGBench's
defaults, used by its GCIVL, GCIQL and GCBC: value goals ``(0.2, 0.5, geometric)``, actor
goals ``(0, 1, uniform)``; its QRL's value goals are random states ``(0, 0)``.  On its stitch
datasets (``impls/hyperparameters.sh``) every baseline but GCBC takes actor goals
``actor_p_randomgoal = actor_p_trajgoal = 0.5``: :func:`actor_goals` (the agents'
``actor_p_randomgoal``).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from lazyq_jax.agents.common import check, check_range, take
from lazyq_jax.config import ConfigError
from lazyq_jax.types import Transitions

GOAL_SOURCES = ("auto", "trajectories", "rows")


@dataclasses.dataclass(frozen=True)
class GoalMix:
    """One of OGBench's goal distributions (module docstring)."""

    p_cur: float
    p_traj: float
    geom: bool


VALUE_GOALS = GoalMix(p_cur=0.2, p_traj=0.5, geom=True)
ACTOR_GOALS = GoalMix(p_cur=0.0, p_traj=1.0, geom=False)


def actor_goals(p_random: float) -> GoalMix:
    """OGBench's actor goals with ``actor_p_randomgoal = p_random`` (``impls/agents/*.py``
    configs, ``GCDataset.sample``): ``actor_p_curgoal`` 0, ``actor_p_trajgoal = 1 - p_random``
    (a uniform later state of the trajectory: ``actor_geom_sample`` False), a random state
    with ``p_random``.  ``actor_goals(0.0)`` is :data:`ACTOR_GOALS` (OGBench's defaults);
    its stitch datasets use 0.5 for every baseline but GCBC (``impls/hyperparameters.sh``)."""
    return GoalMix(p_cur=0.0, p_traj=1.0 - p_random, geom=False)


def check_actor_goals(obj, name: str = "actor_p_randomgoal") -> None:
    """``obj.<name>`` (the probability of a random actor goal, :func:`actor_goals`) in
    ``[0, 1]``; above 0 it needs goals drawn from the trajectories, so ``obj.goals`` (where the
    config has one) must not be ``"rows"``."""
    check_range(obj, name, 0.0, 1.0)
    value, source = getattr(obj, name), getattr(obj, "goals", "trajectories")
    check(value == 0.0 or source != "rows",
          f"{type(obj).__name__}.{name}={value!r} draws random actor goals among the "
          "trajectories' states, but goals='rows' keeps the rows' own goals: use goals='auto' "
          f"or 'trajectories' (trajectory data), or {name}=0")


def check_goal_source(obj, name: str = "goals") -> None:
    value = getattr(obj, name)
    if value not in GOAL_SOURCES:
        raise ConfigError(f"{type(obj).__name__}.{name} must be one of {GOAL_SOURCES}, got {value!r}")


def uses_trajectories(source: str, data: Transitions, who: str) -> bool:
    """Whether an agent draws its goals from the trajectories (``source`` ``"auto"``: when the
    data have them; ``"trajectories"`` requires them; ``"rows"``: the rows' own goals)."""
    if source == "trajectories" and data.traj_last is None:
        raise ValueError(f"{who}: goals='trajectories' needs trajectory data (Transitions.traj_last); "
                         "these data have none: use goals='rows' (the rows' own goals)")
    use = source != "rows" and data.traj_last is not None and data.g is not None
    if use and (data.g.ndim != 2 or data.g.shape[1] != data.s.shape[1]):
        raise ValueError(f"{who}: goals drawn from trajectories are states, but the goals are "
                         f"{tuple(data.g.shape)} and the states {tuple(data.s.shape)}; use goals='rows'")
    return use


def sample_goal_rows(key: jax.Array, idx: jax.Array, last: jax.Array, n_valid: jax.Array,
                     mix: GoalMix, discount: float) -> jax.Array:
    """Goal rows ``[B]`` for rows ``idx [B]`` (``last``: ``traj_last`` of the data), as
    ``GCDataset.sample_goals`` (module docstring); random goals among the rows ``< n_valid``."""
    return sample_goal_rows_and_random(key, idx, last, n_valid, mix, discount)[0]


def sample_goal_rows_and_random(key: jax.Array, idx: jax.Array, last: jax.Array,
                                n_valid: jax.Array, mix: GoalMix, discount: float
                                ) -> tuple[jax.Array, jax.Array]:
    """:func:`sample_goal_rows` and ``[B]`` whether each goal is a random row (not the row
    itself, not a later row of its trajectory: OGBench's ``random_goal_idxs`` picked), which
    ``HGCDataset.sample`` needs for its high-level targets (:meth:`HIQL.batch`).  As
    ``GCDataset.sample_goals``: a trajectory goal with ``p_traj / (1 - p_cur)``, else a random
    one, then the row itself with ``p_cur``; so ``p_random = 1 - p_cur - p_traj`` (OGBench
    reads its ``p_randomgoal`` only in the assertion that the three sum to 1)."""
    k_rand, k_off, k_traj, k_cur = jax.random.split(key, 4)
    final = last[idx]
    rand = jax.random.randint(k_rand, idx.shape, 0, jnp.maximum(n_valid, 1))
    if mix.geom:
        offsets = jax.random.geometric(k_off, 1.0 - discount, idx.shape, dtype=jnp.int32)
        traj = jnp.minimum(idx + offsets, final)
    else:
        d = jax.random.uniform(k_off, idx.shape)
        traj = jnp.round(jnp.minimum(idx + 1, final) * d + final * (1.0 - d)).astype(idx.dtype)
    if mix.p_cur >= 1.0:
        return idx, jnp.zeros(idx.shape, bool)
    pick_traj = jax.random.uniform(k_traj, idx.shape) < mix.p_traj / (1.0 - mix.p_cur)
    pick_cur = jax.random.uniform(k_cur, idx.shape) < mix.p_cur
    return jnp.where(pick_cur, idx, jnp.where(pick_traj, traj, rand)), ~pick_cur & ~pick_traj


def minibatches(source: str, data: Transitions, idx: jax.Array, key: jax.Array,
                n_valid: jax.Array, discount: float, who: str, value: GoalMix = VALUE_GOALS,
                actor: GoalMix = ACTOR_GOALS) -> tuple[Transitions, Transitions]:
    """``(value batch, actor batch)`` of rows ``idx`` for a goal-conditioned agent: OGBench's
    fresh goals (``value``, ``actor``: the agent's mixtures) from the trajectories
    (:func:`goal_batches`) if ``source`` and the data say so (:func:`uses_trajectories`), else
    the rows as they are, twice: then ``actor`` must be :data:`ACTOR_GOALS` (an agent's
    ``actor_p_randomgoal`` 0), else ``ValueError`` (random actor goals need the trajectories)."""
    if uses_trajectories(source, data, who):
        return goal_batches(data, idx, key, n_valid, discount, value, actor)
    if actor != ACTOR_GOALS:
        raise ValueError(f"{who}: actor goals {actor} (actor_p_randomgoal = "
                         f"{1.0 - actor.p_cur - actor.p_traj:g}) are drawn from the trajectories, "
                         "but these data give the rows' own goals (no Transitions.traj_last, or "
                         "goals that are not states): set actor_p_randomgoal=0")
    rows = take(data, idx)
    return rows, rows


def goal_batches(data: Transitions, idx: jax.Array, key: jax.Array, n_valid: jax.Array,
                 discount: float, value: GoalMix = VALUE_GOALS, actor: GoalMix = ACTOR_GOALS
                 ) -> tuple[Transitions, Transitions]:
    """``(value batch, actor batch)`` of rows ``idx``: their transitions with fresh value goals
    (and the reward and ``done`` of those goals) and with fresh actor goals."""
    k_value, k_actor = jax.random.split(key)
    rows = take(data, idx)
    g, r, done = fresh_goals(data, idx, k_value, n_valid, discount, value)
    g_actor = sample_goal_rows(k_actor, idx, data.traj_last, n_valid, actor, discount)
    return rows.replace(g=g, r=r, done=done), rows.replace(g=data.s[g_actor])


def fresh_goals(data: Transitions, idx: jax.Array, key: jax.Array, n_valid: jax.Array,
                discount: float, mix: GoalMix = VALUE_GOALS) -> tuple[jax.Array, jax.Array, jax.Array]:
    """``(g, r, done)`` of rows ``idx`` with fresh goals drawn from ``mix``: the goal row's
    state, ``r = success - 1`` and ``done = success`` (module docstring)."""
    goal = sample_goal_rows(key, idx, data.traj_last, n_valid, mix, discount)
    success = goal == idx
    return data.s[goal], success.astype(jnp.float32) - 1.0, success
