"""References for the agents: the chance level and synthetic tasks with a known optimum.

:class:`RandomAgent` (``random_policy``) acts uniformly at random in the action set and
learns nothing (``blocks = 0``): the chance level of every evaluation.

:func:`line_task` ("cross the line", the task of ``tests/test_baselines.py`` generalised
to ``d`` dimensions): states uniform in ``[-1, 1]^d``, a goal direction ``u``; a move
``a`` of length ``c`` in a uniformly random direction gives ``s' = s + a``; reward 1 and
done when ``s' . u > 0.5``, else 0 and not done.  The data keeps the rows with
``s . u`` in ``[-0.5, 0.5]`` (before the line, at most ~10 moves from it).  From
``s . u`` in ``[0, 0.45]`` (:func:`line_probes`) the line is 1-5 moves away; with
``d = (0.5 - s . u) / c = n + f`` (``0 < f <= 1``) the optimal actions (the fewest moves)
are exactly the cone ``cos(a, u) >= f`` around ``u``, so a greedy argmax of a smooth Q
and an advantage-weighted mean direction both point along ``u``; :func:`score` counts
the probe actions within 26 degrees of ``u`` (the push task's reward cone, arccos 0.9).
Goals: ``"angle"`` (``d = 2``, ``g`` an angle, ``u = (cos g, sin g)``), ``"vector"``
(``g = u`` one of ``n_goals`` fixed unit vectors, so that a small dataset covers each
goal) or ``None`` (one fixed ``u``).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from lazyq_jax.agents.base import Act, Agent, Problem, Spec
from lazyq_jax.agents.common import random_actions
from lazyq_jax.types import Transitions

TOLERANCE_DEG = 26.0  # the push task's reward cone, arccos 0.9 = 25.8 degrees
LINE = 0.5


# ----------------------------------------------------------------------------- chance level


def random_policy(problem: Problem, action_dim: int) -> Act:
    """``act(key, s[B, d_s], g) -> actions [B, action_dim]``: uniform in the action set
    (on the sphere ``|a| = c`` or in the box ``[-c, c]^n_a``); the key matters."""
    return lambda key, s, g: random_actions(key, problem, (s.shape[0], action_dim))


@struct.dataclass
class RandomState:
    """What the random agent keeps of the data: an action of its size (zeros ``[n_a]``)."""

    action: jax.Array


class RandomAgent(Agent):
    """The chance level as an :class:`~lazyq_jax.agents.base.Agent`: ``blocks = 0``, no
    training; ``act`` draws uniform actions of the set from its key."""

    name = "random"
    blocks = 0

    def __init__(self, config: None = None, problem: Problem | None = None,
                 progress: Any = None) -> None:
        if config is not None:
            raise TypeError(f"agent 'random' takes no config, got {type(config).__name__}")
        problem = Problem() if problem is None else problem
        if not isinstance(problem, Problem):
            raise TypeError(f"agent 'random' needs a Problem, got {type(problem).__name__}")
        self.config, self.problem = None, problem

    def init(self, key: jax.Array, data: Transitions) -> RandomState:
        return RandomState(jnp.zeros((Spec.of(data).action_dim,), jnp.float32))

    def run_block(self, state, data, aux=None, n_valid=None):
        return state, {}

    def act(self, policy: RandomState) -> Act:
        return random_policy(self.problem, policy.action.shape[-1])


def make(config: None = None, problem: Problem | None = None, progress: Any = None
         ) -> RandomAgent:
    return RandomAgent(config, problem, progress)


# ----------------------------------------------------------------------------- line tasks


def goal_directions(d: int, n_goals: int, seed: int = 0) -> np.ndarray:
    """``n_goals`` fixed unit vectors in ``R^d`` (normalised Gaussians of ``seed``)."""
    u = np.random.default_rng(seed).normal(size=(n_goals, d))
    return (u / np.linalg.norm(u, axis=1, keepdims=True)).astype(np.float32)


def _goals(rng: np.random.Generator, n: int, d: int, goal: str | None, n_goals: int):
    """``(g, u)``: ``n`` goals and their directions."""
    if goal == "angle":
        if d != 2:
            raise ValueError(f"angle goals need d = 2, got d = {d}")
        g = rng.uniform(-np.pi, np.pi, n).astype(np.float32)
        return g, np.stack([np.cos(g), np.sin(g)], 1).astype(np.float32)
    if goal == "vector":
        u = goal_directions(d, n_goals)[rng.integers(0, n_goals, n)]
        return u, u
    if goal is None:
        u = np.broadcast_to(np.ones(d, np.float32) / np.sqrt(d), (n, d))
        return None, u
    raise ValueError(f"goal must be 'angle', 'vector' or None, got {goal!r}")


def line_task(seed: int, n: int, d: int = 2, goal: str | None = "angle", *,
              action_length: float = 0.1, n_goals: int = 16,
              band: tuple[float, float] = (-LINE, LINE)) -> Transitions:
    """``n`` transitions of the line task (see the module docstring): ``s[n, d]``, random
    moves ``a[n, d]`` of length ``action_length``, goals of kind ``goal``; the rows keep
    ``s . u`` in ``band`` (default ``[-0.5, 0.5]``: at most ~10 moves from the line;
    ``(0, 0.5)``: at most 5, denser data for small tests)."""
    rng = np.random.default_rng(seed)
    lo, hi = band
    m = int(4 * n / min(1.0, hi - lo))  # about 60 % (d = 2) to 50 % (d = 3) per unit of band
    s = rng.uniform(-1, 1, (m, d)).astype(np.float32)
    g, u = _goals(rng, m, d, goal, n_goals)
    proj = np.sum(s * u, 1)
    keep = np.nonzero((proj >= lo) & (proj <= hi))[0][:n]
    if len(keep) < n:
        raise ValueError(f"too few candidates for {n} rows in d = {d}")
    s, u, g = s[keep], u[keep], None if g is None else g[keep]
    a = rng.normal(size=(n, d))
    a = (action_length * a / np.linalg.norm(a, axis=1, keepdims=True)).astype(np.float32)
    s_next = s + a
    done = np.sum(s_next * u, 1) > LINE
    return Transitions(s=jnp.asarray(s), a=jnp.asarray(a), s_next=jnp.asarray(s_next),
                       r=jnp.asarray(done, jnp.float32), g=None if g is None else jnp.asarray(g),
                       done=jnp.asarray(done))


def line_probes(n: int = 2000, d: int = 2, goal: str | None = "angle", seed: int = 12345,
                n_goals: int = 16):
    """``(s[n, d], g, u[n, d])``: probe states with ``s . u`` in ``[0, 0.45]`` (1-5 moves
    from the line), their goals and optimal directions."""
    rng = np.random.default_rng(seed)
    s = rng.uniform(-1, 1, (16 * n, d)).astype(np.float32)
    g, u = _goals(rng, 16 * n, d, goal, n_goals)
    proj = np.sum(s * u, 1)
    keep = np.nonzero((proj >= 0) & (proj <= 0.45))[0][:n]
    return s[keep], None if g is None else g[keep], np.ascontiguousarray(u[keep])


def score(actions: Any, u: np.ndarray) -> tuple[float, float]:
    """``(fraction of actions within 26 degrees of u, median cos(action, u))``."""
    a = np.asarray(actions, np.float64)
    norm = np.maximum(np.linalg.norm(a, axis=1), 1e-30)
    cos = np.sum(a * u, 1) / norm
    return float(np.mean(cos > np.cos(np.radians(TOLERANCE_DEG)))), float(np.median(cos))
