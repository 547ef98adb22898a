"""What every agent is: lazy Q and each baseline behind one interface (one file per agent).

An agent learns from :class:`~lazyq_jax.types.Transitions` of any shape (states
``s[N, d_s]``, actions ``a[N, n_a]``, goals an angle ``g[N]``, a vector ``g[N, d_g]`` or
``None``) and takes every size from the data it is given, as OGBench's agents take
them from example batches: nothing in an agent knows the task.  What it needs to know
of the task besides the data is a :class:`Problem` (the action set, input scales).

Training is a sequence of ``blocks`` (lazy Q: its cycles; a baseline: equal shares of
its gradient steps), each one pure call ``run_block(state, data, aux, n_valid) ->
(state, metrics)`` that ``jax.vmap`` batches over seeds; between blocks the runner
checkpoints, logs and, for lazy Q, runs the host-side neighbour search
(``prepare``).  ``train(key, data)`` runs all blocks in one ``lax.scan`` for users who
want a single pure function.

Acting: ``policies(states, data, n_valid)`` turns trained states (stacked over seeds)
into what acting needs (lazy Q: its dataset's index and values; a baseline: the state
itself), and ``act(policy) -> act(key, s[B, d_s], g) -> actions [B, n_a]`` is pure,
deterministic for the learned baselines and never NaN.  A zero action means "no
move" (lazy Q with ``neighbours.no_model_action="zero"``: no neighbourhood within
``neighbours.max_level`` growths, or every neighbour took the same action).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from lazyq_jax.config import ConfigError
from lazyq_jax.types import Transitions

Act = Callable[[jax.Array, jax.Array, "jax.Array | None"], jax.Array]
ACTION_SETS = ("ball", "box")


@dataclasses.dataclass(frozen=True)
class Problem:
    """What an agent is told about a task besides its data.

    Attributes:
      action_length: ``c``.  ``action_set = "ball"``: the actions are the ball
        ``|a| <= c`` (the paper's Eq. 7: ``max_a beta.a = c |beta|``; every task here
        moves by exactly ``c``); ``"box"``: ``|a_i| <= c`` per component
        (``max_a beta.a = c sum_i |beta_i|``).
      state_scale: states are divided by it (a number, or one per state dimension)
        before any network sees them.
      probes: ``(s[P, d_s], g)``: states whose values lazy Q logs every cycle.
      search_bounds: fixed bounds ``(x_min, y_min, x_max, y_max)`` of the neighbour
        grid for 2-D states with angle goals (so that seeds share compiled searches).
      features: ``phi(s [..., d_s]) -> [..., m]``, where lazy Q measures the state
        distance of its neighbourhoods (None: the state itself).
      goal_features: ``psi(g [..., d_g]) -> [..., m_g]``, where lazy Q measures the goal
        distance of its neighbourhoods, in training and in the policy's queries (None: the
        goal itself).  For goals too wide for a neighbour search (OGBench's 28-D goal
        observations: ``psi`` = what success reads of them, the cube's position).  The
        networks and the local fits' values still see the whole goal.
      state_goal_reward: the reward and termination of a transition are functions of its
        state and goal alone (OGBench's relabelled goal reaching: -1 until the goal is the
        state), so a neighbour's next state may be valued at another row's goal with that
        row's reward (lazy Q's ``train.bootstrap_goal="row"``).
    """

    action_length: float = 0.1
    action_set: str = "ball"
    state_scale: float | tuple[float, ...] = 1.0
    probes: tuple | None = None
    search_bounds: tuple[float, float, float, float] | None = None
    features: Callable | None = None
    goal_features: Callable | None = None
    state_goal_reward: bool = False

    def __post_init__(self) -> None:
        c = self.action_length
        if not (isinstance(c, (int, float)) and not isinstance(c, bool) and math.isfinite(c) and c > 0):
            raise ConfigError(f"Problem.action_length must be a finite number > 0, got {c!r}")
        if self.action_set not in ACTION_SETS:
            raise ConfigError(f"Problem.action_set must be one of {ACTION_SETS}, got {self.action_set!r}")
        scale = np.asarray(self.state_scale, np.float64)
        if scale.ndim > 1 or not np.all(np.isfinite(scale)) or not np.all(scale > 0):
            raise ConfigError(f"Problem.state_scale must be a number > 0 or one per state "
                              f"dimension, got {self.state_scale!r}")
        object.__setattr__(self, "action_length", float(c))
        if scale.ndim == 1:
            object.__setattr__(self, "state_scale", tuple(float(x) for x in scale))
        else:
            object.__setattr__(self, "state_scale", float(scale))


@dataclasses.dataclass(frozen=True)
class Spec:
    """The sizes of a dataset: ``state_dim`` (d_s), ``action_dim`` (n_a) and the goal kind
    (``"angle"`` for ``g[N]``, an int ``d_g`` for ``g[N, d_g]``, ``None`` for no goal)."""

    state_dim: int
    action_dim: int
    goal: str | int | None

    @classmethod
    def of(cls, data: Transitions) -> "Spec":
        s, a, g = np.shape(data.s), np.shape(data.a), None if data.g is None else np.shape(data.g)
        if len(s) != 2 or len(a) != 2 or s[0] != a[0]:
            raise ValueError(f"need states [N, d_s] and actions [N, n_a], got {s} and {a}")
        if g is not None and (len(g) not in (1, 2) or g[0] != s[0]):
            raise ValueError(f"goals must be [N] (an angle) or [N, d_g] (a vector), got {g} "
                             f"for N = {s[0]}")
        goal = None if g is None else ("angle" if len(g) == 1 else int(g[1]))
        return cls(int(s[1]), int(a[1]), goal)

    @classmethod
    def from_dict(cls, d: dict) -> "Spec":
        return cls(int(d["state_dim"]), int(d["action_dim"]), d["goal"])

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def describe(self) -> str:
        goal = {None: "no goal", "angle": "angle goals g[N]"}.get(self.goal, f"goals g[N, {self.goal}]")
        return f"states s[N, {self.state_dim}], actions a[N, {self.action_dim}], {goal}"

    def example(self, n: int = 1) -> Transitions:
        """Zeros of these sizes (``n`` rows): for abstract shapes (``jax.eval_shape``)."""
        s = jnp.zeros((n, self.state_dim), jnp.float32)
        g = None if self.goal is None else jnp.zeros((n,) if self.goal == "angle" else (n, self.goal))
        return Transitions(s=s, a=jnp.zeros((n, self.action_dim), jnp.float32), s_next=s,
                           r=jnp.zeros((n,), jnp.float32), g=g, done=jnp.zeros((n,), bool))

    def check(self, data: Transitions, who: str) -> None:
        """``ValueError`` naming both sizes when ``data`` is not of these sizes."""
        found = Spec.of(data)
        if found != self:
            raise ValueError(f"{who} was built for {self.describe()} but got {found.describe()}; "
                             "build it for this data (sizes come from the data when not given)")


def check_params_fit(params: Any, width: int, who: str, spec: Spec | None = None) -> None:
    """``ValueError`` if the first Dense kernel of ``params`` expects another input width
    than ``width`` (a state trained on data of other sizes), instead of flax's shape error."""
    kernels = [leaf for path, leaf in jax.tree_util.tree_leaves_with_path(params)
               if str(getattr(path[-1], "key", "")) == "kernel"]
    if kernels and int(kernels[0].shape[-2]) != width:
        sizes = f" ({spec.describe()})" if spec is not None else ""
        raise ValueError(f"{who}: its parameters take network inputs of width "
                         f"{int(kernels[0].shape[-2])}, but the data{sizes} encode to width {width}; "
                         "was the state trained on data of other sizes?")


def valid_rows(data: Transitions, n_valid: Any) -> jax.Array:
    """``n_valid`` as an int32 scalar, or the number of rows of ``data`` if None."""
    return jnp.asarray(data.r.shape[0] if n_valid is None else n_valid, jnp.int32)


class Agent:
    """Base of every agent (see the module docstring); subclasses set ``name``, ``config``,
    ``problem``, ``blocks`` and implement :meth:`init`, :meth:`run_block` and :meth:`act`.

    ``train_key_salt``: folded into a seed's training key, so that different methods on
    the same seed draw independent streams (the baselines use a hash of their name).
    """

    name: str = "agent"
    config: Any = None
    problem: Problem = Problem()
    blocks: int = 1

    # --- training
    def check_data(self, spec: Spec) -> None:
        """``ValueError`` saying why, when this agent cannot learn from data of these sizes
        (the runner asks every method before it trains any).  Default: any sizes."""

    def init(self, key: jax.Array, data: Transitions) -> Any:
        """The initial state, sized from ``data`` (its shapes only)."""
        raise NotImplementedError

    def run_block(self, state: Any, data: Transitions, aux: Any, n_valid: Any = None
                  ) -> tuple[Any, dict]:
        """One block of training (pure; vmappable over seeds).  Rows ``>= n_valid`` of a
        padded ``data`` are never trained on."""
        raise NotImplementedError

    def prepare(self, seed: int, data: Transitions, n_valid: int, block: int) -> Any:
        """Host-side work before ``block`` for one seed (lazy Q: the neighbourhoods); the
        result is passed to :meth:`run_block` as ``aux`` (stacked over seeds)."""
        return None

    def refresh(self, block: int) -> bool:
        """Whether :meth:`prepare` must run again before ``block`` (it always runs before
        the first block of a call, and after the data changed)."""
        return False

    def train(self, key: jax.Array, data: Transitions, n_valid: Any = None, aux: Any = None):
        """All blocks in one ``lax.scan``: ``(state, metrics [blocks, ...])``; pure, so
        ``jax.vmap`` it over keys (and over datasets padded to one length with their
        ``n_valid``).  ``aux`` is held fixed (lazy Q: pass the neighbourhoods)."""
        state = self.init(key, data)
        return jax.lax.scan(lambda st, _: self.run_block(st, data, aux, n_valid), state, None,
                            length=self.blocks)

    # --- acting
    def policies(self, states: Any, data: Transitions, n_valid: jax.Array) -> Any:
        """What :meth:`act` needs, for trained ``states`` stacked over seeds, with the
        seeds' datasets stacked (padded) and their sizes ``n_valid [S]``."""
        return states

    def act(self, policy: Any) -> Act:
        """``act(key, s[B, d_s], g) -> actions [B, n_a]`` of one seed's ``policy`` (pure)."""
        raise NotImplementedError

    def policy(self, state: Any, data: Transitions | None = None) -> Act:
        """The ``act`` of one trained (unstacked) ``state`` (``data``: its training data,
        which lazy Q acts on)."""
        stack = lambda tree: jax.tree.map(lambda x: x[None], tree)
        n_valid = None if data is None else jnp.asarray([data.r.shape[0]], jnp.int32)
        policy = self.policies(stack(state), None if data is None else stack(data), n_valid)
        return self.act(jax.tree.map(lambda x: x[0], policy))


def stack_trees(trees: Sequence[Any]) -> Any:
    """Pytrees of equal structure and shapes stacked on a new leading axis."""
    return jax.tree.map(lambda *xs: jnp.stack(xs), *trees)


class FixedPolicy(Agent):
    """An agent that learns nothing and acts with a given ``act`` (a task's scripted
    controller): ``blocks = 0``; its state is an empty array."""

    blocks = 0

    def __init__(self, name: str, act: Act, problem: Problem = Problem()):
        self.name, self._act, self.problem = name, act, problem

    def init(self, key, data):
        return jnp.zeros((0,), jnp.float32)

    def run_block(self, state, data, aux, n_valid=None):
        return state, {}

    def act(self, policy):
        return self._act
