"""Lazy Q (Schubert & Toussaint, 2020): an eagerly learned V(s, g) and a lazily fitted local
action value model Q(s, a, g) ~ alpha + beta.a (Eq. 4), behind the agent interface.

* ``prepare`` (host side, per seed): the neighbourhoods B(s, g) of §V-A-2 of every
  transition (:func:`lazyq_jax.neighbours.find_neighbours`; for 2-D states with angle
  goals the grid over the task's fixed bounds, so that seeds share compiled passes);
  they depend on the data only, so they are found once (``train.resample_neighbours``:
  a fresh k-subset every cycle; ``train.relabel_every``: every row a fresh goal, drawn as
  OGBench's value goals from its trajectory, and new neighbourhoods, every that many cycles).
* ``run_block``: one cycle of fitted value iteration (:func:`lazyq_jax.train.make_train`):
  targets of Eq. (11) (or Eq. 13 with ``train.double_dqn``; ``train.target_max`` moves
  Eq. 7's maximum to the neighbours' actions or an in-sample expectile;
  ``train.bootstrap_goal="row"`` values the neighbours at the row's goal;
  ``train.target_steps`` takes each neighbour's multi-step return along its trajectory,
  :func:`lazyq_jax.targets.multi_step_transitions`) from the network
  frozen at the start of the cycle, then ``train.epochs`` epochs of Adam on Eq. (10).
* ``act``: Eq. (9), the greedy action of the local fit over the dataset
  (:func:`lazyq_jax.policy.lazy_policy`); where the local model prefers no action (no
  neighbourhood within ``neighbours.max_level`` growths, or ``beta = 0``) the zero action,
  or a random one (``neighbours.no_model_action``).  With ``neighbours.subgoal_steps`` the
  step goes towards a subgoal among the data's states (:func:`lazyq_jax.policy.lazy_subgoals`).
"""

from __future__ import annotations

import dataclasses
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh

from lazyq_jax.agents.base import Agent, Problem
from lazyq_jax.agents.goals import fresh_goals, uses_trajectories
from lazyq_jax.config import ConfigError, NeighbourConfig, TrainConfig
from lazyq_jax.keys import purpose_key
from lazyq_jax.local_model import epanechnikov_weights
from lazyq_jax.neighbours import build_index, find_neighbours, is_grid_space, search_all
from lazyq_jax.neighbours.query import stack_policy_indices
from lazyq_jax.parallel import over_seeds
from lazyq_jax.policy import FitKernel, LazyPolicy, lazy_policy, policy_index
from lazyq_jax.targets import bootstrap_table
from lazyq_jax.train import make_train
from lazyq_jax.types import Transitions


@dataclasses.dataclass(frozen=True)
class LazyConfig:
    """Lazy Q's settings: the ``train`` and ``neighbours`` sections of a run config."""

    train: TrainConfig = TrainConfig()
    neighbours: NeighbourConfig = NeighbourConfig()


@jax.tree_util.register_dataclass
@dataclasses.dataclass
class Neighbourhoods:
    """``idx [N, k]`` of every transition's neighbourhood, its growth ``level [N]`` and, with
    ``neighbours.fit_weights="epanechnikov"``, the local fits' ``weights [N, k]``; with
    ``train.relabel_every``, the goals ``g``, rewards ``r`` and ``done`` that the cycles train
    on (the rows' own in the first period, fresh ones later; the neighbourhoods are theirs);
    ``projection``: the local fits' data-only part (:func:`lazyq_jax.targets.fit_projection`),
    found with the neighbourhoods and used by every cycle until the next ones."""

    idx: jax.Array
    level: jax.Array
    weights: jax.Array | None = None
    g: jax.Array | None = None
    r: jax.Array | None = None
    done: jax.Array | None = None
    projection: jax.Array | None = None

    def on(self, data: Transitions) -> Transitions:
        """``data`` with the fresh goals, if any."""
        return data if self.g is None else data.replace(g=self.g, r=self.r, done=self.done)


class LazyAgent(Agent):
    """Lazy Q (see the module docstring).  ``mesh``: data-parallel training and search over
    its devices (one seed at a time; see :func:`lazyq_jax.train.make_train`)."""

    name = "lazy"

    def __init__(self, config: LazyConfig, problem: Problem, *, mesh: Mesh | None = None):
        if not isinstance(config, LazyConfig):
            raise TypeError(f"lazy Q needs a LazyConfig (or None), got {type(config).__name__}")
        self.config, self.problem, self.mesh = config, problem, mesh
        self.row_goal = config.train.bootstrap_goal == "row"
        if self.row_goal and not problem.state_goal_reward:
            raise ConfigError("train.bootstrap_goal='row' values a neighbour's next state at the row's "
                              "goal with the row's reward, which is exact only where the reward depends "
                              "on the state and goal alone; this task's does not "
                              "(Problem.state_goal_reward=False): use bootstrap_goal='neighbour'")
        self.blocks = config.train.cycles
        self.trainer = make_train(config.train, problem.action_length, action_set=problem.action_set,
                                  state_offsets=config.neighbours.local_model != "action",
                                  goal_offsets=config.neighbours.local_model == "action+state+goal",
                                  state_scale=problem.state_scale, probes=problem.probes, mesh=mesh)
        # The local fits' data-only part, once a neighbourhood set (None where not used).
        self._project = jax.jit(self.trainer.projection)
        self.subgoal_steps = config.neighbours.subgoal_steps
        # The policy values the neighbours at each step (at the query's goal with
        # bootstrap_goal="row", at a subgoal with subgoal_steps) rather than from the table.
        self.per_step = self.row_goal or self.subgoal_steps > 0
        # The trained network's inference forward pass, which the policy then calls (one
        # object, so that the policy's static field compares equal).
        self.value_apply = partial(self.trainer.network.apply, train=False) if self.per_step else None

    # --- training
    def init(self, key, data: Transitions):
        self.check_k(data)
        self.check_subgoals(data)
        self.check_target_steps(data)
        if self.config.train.relabel_every:
            uses_trajectories("trajectories", data, "lazy Q's train.relabel_every")
        return self.trainer.init(key, data)

    def check_k(self, data: Transitions) -> None:
        """``ValueError`` when ``k`` is below the local model's number of coefficients
        (``1 + n_a``, ``+ d_s`` with state offsets, ``+ d_g`` (1 for an angle) with goal
        offsets): such fits are underdetermined and only the ridge would pick beta."""
        nb = self.config.neighbours
        coef = 1 + np.shape(data.a)[-1]
        if nb.local_model != "action":
            coef += np.shape(data.s)[-1]
        if nb.local_model == "action+state+goal" and data.g is not None:
            coef += 1 if np.ndim(data.g) == 1 else np.shape(data.g)[-1]
        if nb.k < coef:
            raise ValueError(f"neighbours.k={nb.k} is below the {coef} coefficients of the local "
                             f"model {nb.local_model!r} on these data; raise k or choose a smaller "
                             "local_model")

    def check_target_steps(self, data: Transitions, n_valid: int | None = None) -> None:
        """``ConfigError`` when ``train.target_steps > 1`` cannot apply to ``data``: the
        multi-step targets follow the rows' trajectories at the rows' goals
        (:func:`lazyq_jax.targets.multi_step_transitions`), so they need trajectories, goals
        that are states, terminal rows whose state is their goal, and one reward for every
        other row.  (A path also stops at a state equal to its goal in a row that is not
        terminal: a duplicate of the goal's state, 1 row in 1M on the maze's data.)  With
        ``n_valid`` (concrete data) the values of the first ``n_valid`` rows are checked
        too, else only the shapes."""
        steps = self.config.train.target_steps
        if steps == 1:
            return
        fix = "set train.target_steps=1"
        if data.traj_last is None:
            raise ConfigError("train.target_steps > 1 follows the data's trajectories, but these data "
                              f"have none (Transitions.traj_last): {fix}")
        if data.g is None or np.ndim(data.g) != np.ndim(data.s) or np.shape(data.g)[-1] != np.shape(data.s)[-1]:
            raise ConfigError("train.target_steps > 1 stops each path where its state is the row's goal, so "
                              f"the goals must be states (g[N, {np.shape(data.s)[-1]}]); these data have "
                              f"goals {None if data.g is None else tuple(np.shape(data.g))}: {fix}")
        if n_valid is None:
            return
        n = int(n_valid)
        s, g = np.asarray(data.s[:n]), np.asarray(data.g[:n])
        r, done = np.asarray(data.r[:n]), np.asarray(data.done[:n])
        off_goal = done & ~np.all(s == g, axis=-1)
        if np.any(off_goal):
            bad = int(np.flatnonzero(off_goal)[0])
            raise ConfigError(f"train.target_steps > 1 needs terminal rows whose state is their goal "
                              f"(OGBench's relabelled goal reaching); row {bad} is terminal with the state "
                              f"{s[bad].tolist()} and the goal {g[bad].tolist()}: {fix}")
        step_rewards = np.unique(r[~done])
        if step_rewards.size > 1:
            raise ConfigError("train.target_steps > 1 needs one reward for every step before the goal "
                              f"(OGBench's -1); these rows have {step_rewards.size} different ones "
                              f"(e.g. {step_rewards[:3].tolist()}): {fix}")

    def check_value_head(self, data: Transitions, n_valid: int) -> None:
        """``ConfigError`` when ``train.value_head="distance"`` meets rewards outside [-1, 0]:
        its head counts the steps to the goal at -1 a step (V between ``-1 / (1 - gamma)``
        and 0)."""
        if self.config.train.value_head != "distance":
            return
        r = np.asarray(data.r[:int(n_valid)])
        if r.size and (r.min() < -1.0 or r.max() > 0.0):
            raise ConfigError(f"train.value_head='distance' counts the steps to the goal at a reward of "
                              f"-1 a step, so the rewards must lie in [-1, 0]; these lie in "
                              f"[{r.min():g}, {r.max():g}]: set train.value_head=value")

    def check_subgoals(self, data: Transitions) -> None:
        """``ConfigError`` when ``neighbours.subgoal_steps`` cannot apply to ``data``: its
        subgoals are the trajectories' later states, valued as goals."""
        if self.subgoal_steps == 0:
            return
        if data.traj_last is None:
            raise ConfigError("neighbours.subgoal_steps takes its subgoals from the data's trajectories, "
                              "but these data have none (Transitions.traj_last): set "
                              "neighbours.subgoal_steps=0")
        if data.g is None or np.ndim(data.g) != np.ndim(data.s) or np.shape(data.g)[-1] != np.shape(data.s)[-1]:
            raise ConfigError("neighbours.subgoal_steps values states as goals, so the goals must be "
                              f"states (g[N, {np.shape(data.s)[-1]}]); these data have goals "
                              f"{None if data.g is None else tuple(np.shape(data.g))}: set "
                              "neighbours.subgoal_steps=0")

    def refresh(self, block: int) -> bool:
        every = self.config.train.relabel_every
        return self.config.train.resample_neighbours or (every > 0 and block % every == 0)

    def goals_for(self, seed: int, data: Transitions, n_valid: int, block: int) -> dict:
        """``{g, r, done}`` of every row for block ``block`` (``train.relabel_every``): empty
        without it, the rows' own in the first period (the same pytree: one compiled cycle),
        else OGBench's value goals drawn with the seed's ``relabel`` key and the period's
        number (so a resumed run draws the same)."""
        every = self.config.train.relabel_every
        if every == 0:
            return {}
        if block < every:
            return {"g": data.g, "r": data.r, "done": data.done}
        key = jax.random.fold_in(purpose_key(seed, "relabel"), block // every)
        g, r, done = _fresh_goals(data, jnp.arange(data.size, dtype=jnp.int32), key, jnp.int32(n_valid),
                                  discount=self.config.train.gamma)
        return {"g": g, "r": r, "done": done}

    def prepare(self, seed: int, data: Transitions, n_valid: int, block: int) -> Neighbourhoods:
        """The neighbourhoods of the first ``n_valid`` rows of ``data`` (rows past it: 0).
        Block 0 draws them with the seed's ``neighbours`` key; with
        ``resample_neighbours`` block ``b > 0`` draws a fresh sample with its own key; with
        ``relabel_every`` the rows get fresh goals first (:meth:`goals_for`)."""
        key = purpose_key(seed, "neighbours")
        if self.config.train.resample_neighbours and block > 0:
            key = jax.random.fold_in(purpose_key(seed, "resample"), block)
        goals = self.goals_for(seed, data, n_valid, block)
        if block == 0 or goals:  # the rows' goals as they are, or fresh ones (relabel_every)
            self.check_target_steps(data.replace(**goals), n_valid)
            self.check_value_head(data.replace(**goals), n_valid)
        data_g = None if self.row_goal else goals.get("g", data.g)  # row goals: state space only
        nc, n = self.config.neighbours, int(n_valid)
        x, data_g = self.search_space(data.s), self.goal_space(data_g)
        if is_grid_space(x, data_g):
            index = build_index(np.asarray(x[:n]), np.asarray(data_g[:n]), k=nc.k,
                                radius_s=nc.radius_s, radius_g=nc.radius_g, growth=nc.growth,
                                max_level=0, capacity=data.size, bounds=self.problem.search_bounds)
            nb = search_all(index, key, x, data_g, mesh=self.mesh, n_queries=n)
            return self._with_projection(data, Neighbourhoods(
                nb.idx, nb.level, self.fit_weights(x, data_g, nb.idx, nb.level), **goals))
        g = None if data_g is None else data_g[:n]
        nb = find_neighbours(key, x[:n], g, x[:n], g, k=nc.k, radius_s=nc.radius_s,
                             radius_g=nc.radius_g, growth=nc.growth, mesh=self.mesh)
        pad = data.size - n
        idx = jnp.concatenate([nb.idx, jnp.zeros((pad, nc.k), jnp.int32)])
        level = jnp.concatenate([nb.level, jnp.zeros((pad,), jnp.int32)])
        return self._with_projection(data, Neighbourhoods(idx, level, self.fit_weights(x, data_g, idx, level),
                                                          **goals))

    def _with_projection(self, data: Transitions, nb: Neighbourhoods) -> Neighbourhoods:
        """``nb`` with the local fits' projection of its rows (:attr:`Neighbourhoods.projection`)."""
        return dataclasses.replace(nb, projection=self._project(nb.on(data), nb.idx, nb.weights))

    def fit_weights(self, x, g, idx, level):
        """The local fits' weights ``[N, k]`` (``neighbours.fit_weights``; ``None`` when
        uniform) from the search-space points ``x`` and goals ``g`` of every row."""
        nc = self.config.neighbours
        if nc.fit_weights == "uniform":
            return None
        return _weights(jnp.asarray(x, jnp.float32), None if g is None else jnp.asarray(g), idx, level,
                        radius_s=nc.radius_s, radius_g=nc.radius_g, growth=nc.growth)

    def search_space(self, s):
        """Where the state distance of the neighbourhoods is measured: ``problem.features(s)``
        (the task's feature map, computed in float32 on the host's device), else ``s``."""
        phi = self.problem.features
        return s if phi is None else np.asarray(jax.jit(phi)(jnp.asarray(s, jnp.float32)))

    def goal_space(self, g):
        """Where the goal distance of the neighbourhoods is measured:
        ``problem.goal_features(g)`` (float32, on the host's device), else ``g``."""
        psi = self.problem.goal_features
        return g if psi is None or g is None else np.asarray(jax.jit(psi)(jnp.asarray(g, jnp.float32)))

    def run_block(self, state, data: Transitions, aux: Neighbourhoods, n_valid=None):
        data = aux.on(data)
        state, metrics = self.trainer.run_cycle(state, data, aux.idx, n_valid, aux.weights, aux.projection)
        n = data.r.shape[0] if n_valid is None else n_valid
        valid = (jnp.arange(data.r.shape[0]) < n).astype(jnp.float32)
        count = jnp.maximum(jnp.sum(valid), 1.0)
        metrics["neighbour_level_mean"] = jnp.sum(aux.level * valid) / count
        metrics["neighbour_level0_fraction"] = jnp.sum((aux.level == 0) * valid) / count
        return state, metrics

    def train(self, key, data: Transitions, n_valid=None, aux=None):
        """All cycles in one ``lax.scan`` with the neighbourhoods ``aux`` held fixed (an
        ``idx [N, k]`` array or :class:`Neighbourhoods`)."""
        if aux is None:
            raise ValueError("lazy Q's train needs the neighbourhoods: train(key, data, aux=idx) "
                             "with idx = find_neighbours(...).idx")
        if isinstance(aux, Neighbourhoods):
            return self.trainer.train(key, aux.on(data), aux.idx, n_valid, aux.weights)
        if self.config.neighbours.fit_weights != "uniform":
            raise ValueError("neighbours.fit_weights needs the neighbourhoods' levels: pass "
                             "aux=agent.prepare(seed, data, n_valid, 0)")
        return self.trainer.train(key, data, aux, n_valid)

    def value_fn(self, state):
        """``V(s, g)`` of a trained (unstacked) state, in inference mode."""
        return self.trainer.value_fn(state)

    # --- acting
    def policies(self, states, data: Transitions, n_valid) -> LazyPolicy:
        """Each seed's policy over its own dataset (rows ``< n_valid``): the neighbour index
        (stacked over the seeds: one layout and the largest capacities), and the
        bootstrapped values ``r + gamma (1 - done) V(s', g)`` of its trained V (with
        ``train.bootstrap_goal="row"`` instead the index in state space, the next states and
        the trained network, which each step values at the query's goal)."""
        self.check_subgoals(data)
        nc, n_seeds = self.config.neighbours, int(np.shape(n_valid)[0])
        xs = [self.search_space(data.s[i]) for i in range(n_seeds)]
        search_g = None if self.per_step else data.g
        if search_g is not None and self.problem.goal_features is not None:
            search_g = jnp.stack([self.goal_space(data.g[i]) for i in range(n_seeds)])
        indices = [policy_index(xs[i], None if search_g is None else np.asarray(search_g[i]),
                                k=nc.k, radius_s=nc.radius_s, radius_g=nc.radius_g, growth=nc.growth,
                                max_level=nc.max_level, n_valid=int(n_valid[i]))
                   for i in range(n_seeds)]
        # At least the previous call's capacities where the data chose the same layout (online
        # rounds: the rollout compiled for the last round's policy then runs this one); only
        # the shapes are kept.
        index = stack_policy_indices(indices, like=getattr(self, "_policy_like", None))
        self._policy_like = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype), index)
        gamma = self.config.train.gamma
        value_vars = next_states = None
        if self.per_step:  # each step values the neighbours' next states at the query's goal
            values = jnp.zeros(np.shape(data.r), jnp.float32)
            value_vars = {"params": states.params, "batch_stats": states.batch_stats}
            next_states = data.s_next
        else:
            values = over_seeds(lambda st, d: bootstrap_table(self.trainer.value_fn(st), d, gamma),
                                n_seeds)(states, data)
        length = jnp.full(n_seeds, self.problem.action_length, jnp.float32)
        model = self.config.neighbours.local_model
        states = data.s if model != "action" else None
        # (the two-level step values the neighbours at a subgoal, not at their rows' goals)
        goals = data.g if model == "action+state+goal" and self.subgoal_steps == 0 else None
        kernel = None
        if nc.fit_weights != "uniform":
            x = jnp.stack([jnp.asarray(x, jnp.float32) for x in xs])
            kernel = FitKernel(x, search_g, nc.radius_s, nc.radius_g, nc.growth)
        return LazyPolicy(index, data.a, values, length, self.problem.action_set, self.problem.features,
                          states, goals, kernel, nc.no_model_action, next_states, value_vars,
                          self.value_apply, self.subgoal_steps,
                          data.traj_last if self.subgoal_steps else None,
                          None if self.per_step else self.problem.goal_features, nc.greedy,
                          nc.far_subgoal_steps)

    def act(self, policy: LazyPolicy):
        return lambda key, s, g: lazy_policy(policy, key, s, g)[0]


@partial(jax.jit, static_argnames=("radius_s", "radius_g", "growth"))
def _weights(x, g, idx, level, *, radius_s, radius_g, growth):
    return epanechnikov_weights(x[idx], x, None if g is None else g[idx], g, level,
                                radius_s=radius_s, radius_g=radius_g, growth=growth)


_fresh_goals = jax.jit(fresh_goals, static_argnames=("discount", "mix"))


def make(config: LazyConfig | None, problem: Problem, *, mesh: Mesh | None = None) -> LazyAgent:
    return LazyAgent(LazyConfig() if config is None else config, problem, mesh=mesh)

