"""What a task is: everything that only one robot, world or benchmark knows.

A task is one folder under :mod:`lazyq_jax.tasks` with a :class:`Task` subclass and
one line in the registry (:mod:`lazyq_jax.tasks`).  It owns its scene, its data
collection, its evaluation protocols and their summaries, its figures and
animation, its scripted controller (if any), its input scales and probe states, and
the presets of its run :class:`~lazyq_jax.config.Config` (the neighbourhood radii of
its space among them).  The runner (:mod:`lazyq_jax.run`) and the agents
(:mod:`lazyq_jax.agents`) know tasks only through this interface; the core
(neighbours, local model, targets, networks, training, checkpoints) knows none.

Shared here: :func:`make_protocol` / :func:`run_protocol` (batched evaluation episodes,
the physics compiled once per task and shared by every method) and the outcome codes
every protocol reports.
"""

from __future__ import annotations

import dataclasses
import functools
from pathlib import Path
from typing import Any, Callable, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh

from lazyq_jax.agents.base import Act, Problem
from lazyq_jax.config import Config, ConfigError
from lazyq_jax.types import Transitions

NOT_PUSHED, CORRECT, WRONG = 0, 1, 2  # an episode's outcome: none yet / success / failure


class Rollouts(NamedTuple):
    """Batched episodes: ``agent [T + 1, B, d]`` (what the task draws of the agent, e.g. the
    finger or the fingertip), ``obj [T + 1, B, 2]`` (the object it moves, e.g. the disk),
    ``outcome [B]`` (:data:`CORRECT` / :data:`WRONG` / :data:`NOT_PUSHED`), ``steps [B]``
    taken, ``idle [B]`` steps whose action was zero (lazy Q: no local model that prefers
    an action, unless ``neighbours.no_model_action="random"`` moves there),
    ``extra``: what else the task keeps (e.g. the arm's joint angles ``[T + 1, B, 3]``), and
    ``ctx``: the protocol's per-episode context (e.g. goals, or the targets ``[B, 2]``)."""

    agent: Any
    obj: Any
    outcome: Any
    steps: Any
    idle: Any
    extra: Any = None
    ctx: Any = None


class Carry(NamedTuple):
    """What a protocol carries from step to step, for one seed's batch of episodes: the
    env ``state``, the protocol's per-episode ``ctx`` (e.g. goals, targets), and the
    episodes' ``done``, ``outcome``, ``steps`` taken and ``idle`` steps."""

    state: Any
    ctx: Any
    done: jax.Array
    outcome: jax.Array
    steps: jax.Array
    idle: jax.Array


@dataclasses.dataclass(frozen=True)
class Protocol:
    """A batched evaluation protocol as three jitted programs over stacked seeds, which do not
    depend on the agent: ``start(keys [S]) -> carry``, ``observe(carry) -> (s, g)``,
    ``transition(carry, actions) -> (carry, record)``; ``steps`` at most.
    :func:`run_protocol` drives them from the host with the agent's ``act`` in between, so a
    study of many methods compiles the physics once and each method only its policy, and
    a batch stops as soon as every episode has ended."""

    start: Callable
    observe: Callable
    transition: Callable
    record: Callable
    steps: int


def make_protocol(start: Callable, step: Callable, goal_of: Callable, outcome_of: Callable,
                  observe: Callable, record: Callable, steps: int) -> Protocol:
    """A :class:`Protocol` from one seed's unbatched-over-seeds pieces, all over a batch of ``B``
    episodes: ``start(key) -> (state, ctx, done0)`` (``done0``: episodes that succeeded
    before the first step), ``step(state, actions) -> (state, info)``, ``goal_of(state, ctx)
    -> g``, ``outcome_of(info, g, new_state, ctx) -> (outcome, ends)``, ``observe(state) ->
    s``, ``record(state) -> pytree`` (what :class:`Rollouts` keeps per step: ``(agent, obj,
    extra)``).  Finished episodes stay frozen."""

    def first(key):
        state, ctx, done0 = start(key)
        zeros = jnp.zeros(done0.shape, jnp.int32)
        return Carry(state, ctx, done0, jnp.where(done0, CORRECT, NOT_PUSHED), zeros, zeros)

    def transition(c: Carry, action):
        g = goal_of(c.state, c.ctx)
        new_state, info = step(c.state, action)
        new_outcome, ends = outcome_of(info, g, new_state, c.ctx)
        live = ~c.done
        keep = lambda new, old: jnp.where(live.reshape((-1,) + (1,) * (new.ndim - 1)), new, old)
        state = jax.tree.map(keep, new_state, c.state)
        idle = c.idle + (live & jnp.all(action == 0, axis=-1))
        c = Carry(state, c.ctx, c.done | ends, jnp.where(live & ends, new_outcome, c.outcome),
                  c.steps + live, idle)
        return c, record(state)

    return Protocol(start=jax.jit(jax.vmap(first)),
                    observe=jax.jit(jax.vmap(lambda c: (observe(c.state), goal_of(c.state, c.ctx)))),
                    transition=jax.jit(jax.vmap(transition)),
                    record=jax.jit(jax.vmap(lambda c: record(c.state))), steps=steps)


def run_protocol(protocol: Protocol, acts: Callable, policies: Any, keys: jax.Array,
                 check_every: int = 5) -> Rollouts:
    """The episodes of ``protocol`` for stacked seeds: ``keys [S]`` (each seed's protocol key:
    split into a start key and one key per step), ``acts(policies, keys [S], s, g)`` the
    method's actions for every seed (``vmap`` of its ``act``).  Stops once every episode of
    every seed has ended (checked every ``check_every`` steps; the records then repeat the
    final states).  Returns :class:`Rollouts` with a leading seed axis (NumPy)."""
    # Everything on one device, committed: the compiled programs then see the same argument
    # placement at every call (uncommitted and committed arguments compile separately).
    place = lambda x: jax.device_put(x, jax.local_devices()[0])
    k_start, k_run = (jnp.stack(x) for x in zip(*[jax.random.split(k) for k in keys]))
    step_keys = place(jax.vmap(lambda k: jax.random.split(k, protocol.steps))(k_run))  # [S, T, 2]
    policies = place(policies)
    carry = place(protocol.start(k_start))
    records = [protocol.record(carry)]
    for t in range(protocol.steps):
        s, g = protocol.observe(carry)
        carry, rec = protocol.transition(carry, acts(policies, step_keys[:, t], s, g))
        records.append(rec)
        if (t + 1) % check_every == 0 and bool(jnp.all(carry.done)):
            break
    records = jax.device_get(records)
    records += [records[-1]] * (protocol.steps + 1 - len(records))
    agent, obj, extra = (None if records[0][i] is None else np.stack([r[i] for r in records], axis=1)
                         for i in range(3))
    c = jax.device_get(carry)
    return Rollouts(agent, obj, np.asarray(c.outcome), np.asarray(c.steps), np.asarray(c.idle), extra,
                    c.ctx)


@functools.lru_cache(maxsize=32)
def seed_acts(act_of: Callable) -> Callable:
    """``acts(policies, keys [S], s [S, B, ...], g) -> actions [S, B, n_a]``: a method's
    ``act`` over stacked seeds, jitted once per method."""
    return jax.jit(jax.vmap(lambda p, k, s, g: act_of(p)(k, s, g)))


@dataclasses.dataclass
class Evaluation:
    """A task's evaluation of one method on several seeds: ``per_seed`` results (JSON,
    one dict per seed) and ``rollouts`` (stacked over seeds, NumPy) for the figures."""

    per_seed: list[dict]
    rollouts: dict


class Task:
    """Base of every task (see the module docstring).  Subclasses set the attributes and
    implement the methods that raise ``NotImplementedError``.

    Attributes:
      name: the registry name.
      summary: one line for ``--help`` and the docs.
      collect_config, eval_config: the classes of ``Config.collect`` and ``Config.eval``.
      presets: named run configs; ``"paper"`` is the default, ``"smoke"`` a tiny run.
      rates: ``(key, label)`` of the rates the study tables report (mean and 95 % CI
        over seeds), in order; :meth:`seed_rates` gives them per seed.
      directions: whether :meth:`seed_rates` also gives ``per_direction_correct_rate``
        (goal directions of a protocol A), drawn per method in the study.
      online: whether the online data source works (:meth:`explore`).
      data_version: the version of what :meth:`collect` returns; a run directory's cached
        dataset of another version is collected anew (e.g. rows that gained
        ``Transitions.traj_last``).
      published: a public benchmark's published numbers for this task, ``method -> (mean %,
        std % or None)`` of its first rate, from ``published_source`` at ``published_budget``
        (gradient steps, batch size); empty where there are none (``report --suite``).
    """

    name: str = "task"
    summary: str = ""
    collect_config: type = object
    eval_config: type = object
    presets: dict[str, Config] = {}
    rates: tuple[tuple[str, str], ...] = ()
    directions: bool = False
    online: bool = False
    data_version: int = 1
    published: dict[str, tuple[float, float | None]] = {}
    published_source: str = ""
    published_budget: tuple[int, int] | None = None

    # --- configuration
    def check(self, config: Config) -> None:
        """Raise :class:`ConfigError` for settings that do not fit together."""
        if not isinstance(config.collect, self.collect_config) or not isinstance(
                config.eval, self.eval_config):
            raise ConfigError(f"task {self.name!r} needs collect: {self.collect_config.__name__} and "
                              f"eval: {self.eval_config.__name__}, got "
                              f"{type(config.collect).__name__} and {type(config.eval).__name__}")
        if config.online.rounds and not self.online:
            raise ConfigError(f"task {self.name!r} has no online data source; set online.rounds=0")
        self.features(config)

    def problem(self, config: Config) -> Problem:
        """What the agents are told besides the data (action set, input scales, ...)."""
        raise NotImplementedError

    def method_defaults(self, name: str) -> dict:
        """Config fields of baseline ``name`` that this task sets (e.g. a benchmark's published
        network sizes); they replace the ones taken from lazy Q's settings and yield to the
        method's own options (``--methods iql:width=64``).  Default: none."""
        return {}

    def feature_maps(self, config: Config) -> dict[str, Callable | None]:
        """The spaces lazy Q may measure its neighbourhoods in (``neighbours.features``):
        ``name -> phi(s [..., d_s]) -> [..., m]``; ``"state"`` (None: the state itself) always."""
        return {"state": None}

    def features(self, config: Config) -> Callable | None:
        """The feature map ``config.neighbours.features`` names (:class:`ConfigError` listing
        the task's maps if it has none of that name)."""
        maps = self.feature_maps(config)
        name = config.neighbours.features
        if name not in maps:
            raise ConfigError(f"task {self.name!r} has no feature map {name!r} for neighbours.features; "
                              f"its maps: {', '.join(maps)}")
        return maps[name]

    # --- data
    def collect(self, key: jax.Array, config: Config, *, mesh: Mesh | None = None,
                progress: bool = True) -> Transitions:
        """The static dataset of one seed (``key``: its collection key)."""
        raise NotImplementedError

    def data_summary(self, data: Transitions, config: Config) -> dict:
        """Counts of one seed's data (saved beside it; the study reports them)."""
        return {"rows": data.size}

    def data_table(self, summaries: Sequence[dict]) -> dict:
        """The seeds' data summaries for ``results.json``."""
        return {"rows": [s["rows"] for s in summaries]}

    def rows_per_move(self, config: Config) -> int:
        """Dataset rows per simulated move (online budgets are counted in moves)."""
        return 1

    def explore(self, act: Act, key: jax.Array, config: Config) -> dict:
        """One online round of one seed (pure; vmapped over seeds): episodes of ``act``
        with exploration (``config.online``); a dict with ``s, a, s_next, moved [E, T,
        ...]``, ``g, r [E, T, goals, ...]`` (:func:`lazyq_jax.data.episodes_to_transitions`)
        and ``counts``: per-round counts (scalars)."""
        raise NotImplementedError

    # --- evaluation
    def evaluate(self, act_of: Callable[[Any], Act], policies: Any, config: Config,
                 seeds: Sequence[int], *, quick: bool = False) -> Evaluation:
        """Every protocol for several seeds at once: ``policies`` stacked on a leading seed
        axis, ``act_of(policy)`` one seed's :data:`Act`; seed ``s`` is evaluated with the
        episodes of evaluation seed ``s + config.eval.seed``.  ``quick``: the short check
        of an online round."""
        raise NotImplementedError

    def seed_rates(self, result: dict) -> dict:
        """The numbers of one seed's evaluation that the tables report (keys of
        :attr:`rates`, and ``per_direction_correct_rate`` if :attr:`directions`)."""
        raise NotImplementedError

    def log_line(self, result: dict) -> str:
        """One line about one seed's evaluation."""
        rates = self.seed_rates(result)
        return ", ".join(f"{label} {rates[key]:.1%}" for key, label in self.rates
                         if isinstance(rates.get(key), float))

    # --- acting without learning
    def scripted(self, config: Config) -> Act | None:
        """A controller that knows the task (an upper reference; None if there is none)."""
        return None

    # --- figures
    def figures(self, out_dir: Path, result: dict, rollouts: dict, config: Config,
                value_fn: Callable | None = None) -> list[Path]:
        """The task's figures of one seed's evaluation (``value_fn(s, g)``: a learned V to
        draw, if the method has one)."""
        return []

    def animate(self, path: Path, rollouts: dict, config: Config) -> Path | None:
        """A short GIF of a few evaluation rollouts of one seed."""
        return None
