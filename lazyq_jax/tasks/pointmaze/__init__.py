"""OGBench's pointmaze (Park et al. 2024): every ``pointmaze-{medium,large,giant,teleport}-{navigate,
stitch}-v0`` dataset, a public benchmark nobody here wrote.  The task ``pointmaze`` is
``pointmaze-medium-navigate``; each dataset is also a task of its own name (OGBench's id, with or
without ``-v0``), whose presets hold that dataset's recipe and discount.

State: the point's ``(x, y)`` (``d_s = 2``); goal: a position ``g [2]`` (vector goals); action: the
box ``[-1, 1]^2`` (``T(s, a) = s + 0.2 a`` away from walls); reward ``success - 1`` with success
the goal index equal to the transition's (OGBench's ``GCDataset``), discount 0.99.  Data: OGBench's
navigate recipe (or a user's OGBench ``.npz``, ``collect.dataset``) relabelled with OGBench's value
goals; evaluation: OGBench's five tasks, 50 episodes each of at most 1000 steps.  See
:mod:`~lazyq_jax.tasks.pointmaze.maze` (the env), :mod:`~lazyq_jax.tasks.pointmaze.dataset` (the
data) and shared/DESIGN.md §8 (what was checked against OGBench).
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh

from lazyq_jax.agents.base import Problem
from lazyq_jax.config import Config, ConfigError
from lazyq_jax.data import DatasetError
from lazyq_jax.keys import purpose_key
from lazyq_jax.tasks.base import (CORRECT, NOT_PUSHED, Evaluation, Protocol, Task, make_protocol,
                                  run_protocol, seed_acts)
from lazyq_jax.tasks.pointmaze import plots
from lazyq_jax.tasks.pointmaze.config import (DATASETS, PointMazeCollectConfig, PointMazeEvalConfig,
                                              check, dataset_id, discount, presets)
from lazyq_jax.tasks.pointmaze.dataset import (load_npz, navigate, relabel, save_npz, stitch,
                                               trajectory_transitions)
from lazyq_jax.tasks.pointmaze.maze import GOAL_TOL, NOISE, Maze, get_maze
from lazyq_jax.tasks.pointmaze.published import OGBENCH, OGBENCH_BUDGET, PUBLISHED
from lazyq_jax.types import Transitions

__all__ = ["DATASETS", "Maze", "PointMazeCollectConfig", "PointMazeEvalConfig", "PointMazeTask",
           "get_maze", "load_npz", "navigate", "relabel", "save_npz", "stitch", "trajectory_transitions"]

N_TASKS = 5
#: OGBench's agents that take its per-dataset discount and stitch actor goals (all but GCBC)
OGBENCH_VALUE_AGENTS = ("gcivl", "gciql", "qrl", "crl", "hiql")


def seed_rng(key: jax.Array) -> np.random.Generator:
    """A NumPy generator seeded from a JAX key (the host-side data of one seed)."""
    return np.random.default_rng(int(jax.random.randint(key, (), 0, 2**31 - 1)))


def collect_steps(key: jax.Array, collect: PointMazeCollectConfig, progress: bool = False) -> dict:
    """One seed's trajectories as transitions (:func:`trajectory_transitions`): the file
    ``collect.dataset`` if set, else the navigate recipe drawn from ``key``."""
    if collect.dataset is not None:
        raw = load_npz(collect.dataset)
        maze = get_maze(collect.maze)
        cells = maze.xy_to_ij(raw["observations"])
        rows, cols = maze.map.shape
        inside = ((cells >= 0).all(-1) & (cells[:, 0] < rows) & (cells[:, 1] < cols))
        if not inside.all() or (maze.map[cells[inside, 0], cells[inside, 1]] != 0).any():
            raise DatasetError(f"{collect.dataset}: observations lie outside the free cells of the "
                               f"{collect.maze} maze; is it another maze's file? (collect.maze)")
        return trajectory_transitions(raw)
    recipe = navigate if collect.recipe == "navigate" else stitch
    raw = recipe(get_maze(collect.maze), seed_rng(key), collect.episodes, collect.episode_steps,
                 collect.noise, progress=progress)
    return trajectory_transitions(raw)


def host_call(fn: Callable, *args) -> jax.Array:
    """``fn(*numpy args) -> array of args[0]'s shape`` from jitted code (float32), batched over
    any ``vmap`` (``jax.pure_callback``)."""
    out = jax.ShapeDtypeStruct(jnp.shape(args[0]), jnp.float32)
    return jax.pure_callback(lambda *a: np.asarray(fn(*a), np.float32), out, *args,
                             vmap_method="broadcast_all")


def oracle_action(maze: Maze, s, g) -> np.ndarray:
    """The scripted controller's action for ``s, g [..., 2]``."""
    s, g = np.asarray(s, np.float64), np.asarray(g, np.float64)
    flat_s, flat_g = s.reshape(-1, 2), np.broadcast_to(g, s.shape).reshape(-1, 2)
    d = maze.subgoal_direction(flat_s, flat_g)
    here = np.all(maze.xy_to_ij(flat_s) == maze.xy_to_ij(flat_g), axis=-1)
    to_goal = flat_g - flat_s
    d[here] = to_goal[here] / (np.linalg.norm(to_goal[here], axis=-1, keepdims=True) + 1e-6)
    return d.reshape(s.shape)


def native_step(maze: str) -> Callable:
    """``step(qpos [..., 2], actions [..., 2]) -> qpos`` (float32) for jitted code: the maze's
    native batched step through ``jax.pure_callback`` (batched over any ``vmap``)."""
    return lambda q, a: host_call(get_maze(maze).step, q, a)


def teleport_step(maze: str) -> Callable:
    """``step(state, actions) -> state`` of a maze with teleporters for jitted code, ``state =
    (observed qpos [B, 2], teleport pending [B], raw keys [B, 2])``: the point starts from
    an outbound teleporter (``floor(3 u)``, ``u`` from the episode's key) where a move is
    pending, steps natively, and the new step's observation is where it ends
    (:class:`~lazyq_jax.tasks.pointmaze.maze.Maze`)."""
    m, step = get_maze(maze), native_step(maze)

    def go(state, a):
        q, pending, key = state
        key, k_u = jnp.moveaxis(jax.vmap(jax.random.split)(key), 1, 0)
        u = jax.vmap(jax.random.uniform)(k_u)
        start = host_call(lambda q_, p_, u_: m.teleport(q_, p_[..., 0] > 0.5, u_[..., 0]), q,
                          jnp.broadcast_to(pending[..., None], q.shape).astype(jnp.float32), jnp.broadcast_to(u[..., None], q.shape))
        new_q = step(start, a)
        pending = host_call(lambda q_: np.broadcast_to(m.teleport_pending(q_)[..., None], q_.shape),
                            new_q)[..., 0] > 0.5
        return new_q, pending, key

    return go


def task_protocol(maze: str, cfg: PointMazeEvalConfig) -> Protocol:
    """OGBench's evaluation as a :class:`~lazyq_jax.tasks.base.Protocol`: ``episodes_per_task``
    episodes of each of ``cfg.tasks`` side by side; ``ctx``: goals ``[B, 2]`` and task numbers."""
    m = get_maze(maze)
    task_ids = np.repeat(np.asarray(cfg.tasks), cfg.episodes_per_task)
    init = jnp.asarray(m.ij_to_xy(np.asarray([m.tasks[t - 1][0] for t in task_ids])), jnp.float32)
    goal = jnp.asarray(m.ij_to_xy(np.asarray([m.tasks[t - 1][1] for t in task_ids])), jnp.float32)
    b = len(task_ids)
    # The state: the point's position, or (position, teleport pending, key) with teleporters.
    teleports = m.has_teleports
    step_native = teleport_step(maze) if teleports else native_step(maze)
    position = (lambda q: q[0]) if teleports else (lambda q: q)

    def start(key):
        k_s, k_g = jax.random.split(key)
        s = init + jax.random.uniform(k_s, init.shape, jnp.float32, -NOISE, NOISE)
        g = goal + jax.random.uniform(k_g, goal.shape, jnp.float32, -NOISE, NOISE)
        if teleports:  # raw uint32 keys [B, 2], one per episode
            s = (s, jnp.zeros((b,), bool), jax.random.split(jax.random.fold_in(key, 2), b))
        return s, {"goal": g, "task": jnp.asarray(task_ids, jnp.int32)}, jnp.zeros((b,), bool)

    def step(q, a):
        return step_native(q, jnp.clip(a, -1.0, 1.0)), None

    def outcome_of(info, g, new_q, ctx):
        reached = jnp.linalg.norm(position(new_q) - g, axis=-1) <= GOAL_TOL
        return jnp.where(reached, CORRECT, NOT_PUSHED), reached

    return make_protocol(start, step, goal_of=lambda q, ctx: ctx["goal"], outcome_of=outcome_of,
                         observe=position, record=lambda q: (position(q), None, None),
                         steps=cfg.max_steps)


@functools.lru_cache(maxsize=8)
def _protocol(maze: str, cfg: PointMazeEvalConfig) -> Protocol:
    return task_protocol(maze, cfg)


def summarize(rollouts, cfg: PointMazeEvalConfig) -> dict:
    """One seed's evaluation: success rate and mean steps of the successes per task, the mean
    over tasks (OGBench's number), and the share of steps without an action."""
    task = np.asarray(rollouts.ctx["task"])
    success = np.asarray(rollouts.outcome) == CORRECT
    steps = np.asarray(rollouts.steps)
    per_task = []
    for t in cfg.tasks:
        sel = task == t
        per_task.append({"task": int(t), "episodes": int(sel.sum()), "successes": int(success[sel].sum()),
                         "success_rate": float(success[sel].mean()),
                         "mean_steps_of_successes": float(steps[sel & success].mean())
                         if (sel & success).any() else None})
    return {"per_task": per_task, "success_rate": float(np.mean([r["success_rate"] for r in per_task])),
            "idle_fraction": float(np.sum(rollouts.idle) / max(1, np.sum(steps)))}


class PointMazeTask(Task):
    """One of OGBench's pointmaze datasets (see the module docstring): ``maze`` and ``recipe``
    choose the presets' data; ``name`` is the registry's."""

    collect_config = PointMazeCollectConfig
    eval_config = PointMazeEvalConfig
    data_version = 2  # the rows carry their trajectories (Transitions.traj_last)
    rates = (("success_rate", "success (5 tasks)"),
             *((f"task{i}", f"task {i}") for i in range(1, N_TASKS + 1)))

    def __init__(self, maze: str = "medium", recipe: str = "navigate", name: str | None = None):
        self.maze, self.recipe = maze, recipe
        self.dataset = dataset_id(maze, recipe)
        self.name = name or self.dataset
        self.summary = (f"OGBench's {self.dataset}-v0: a point in a maze, vector goals, box actions"
                        + ("" if recipe == "navigate" else "; short trajectories to stitch"))
        self.presets = presets(maze, recipe, self.name)
        self.published = PUBLISHED[self.dataset]
        self.published_source, self.published_budget = OGBENCH, OGBENCH_BUDGET

    def check(self, config: Config) -> None:
        super().check(config)
        check(config)
        c = config.collect
        if (c.maze, c.recipe) != (self.maze, self.recipe):
            raise ConfigError(f"task {self.name} is OGBench's {self.maze} maze with {self.recipe} data, "
                              f"but collect.maze={c.maze!r}, collect.recipe={c.recipe!r}: choose the "
                              f"dataset by its task, --task {dataset_id(c.maze, c.recipe)} (its discount "
                              "and the baselines' flags follow the task)")

    def problem(self, config: Config) -> Problem:
        return Problem(action_length=1.0, action_set="box", state_scale=1.0, state_goal_reward=True)

    def method_defaults(self, name: str) -> dict:
        """OGBench's published network and batch sizes (3 x 512 hidden, batch 1024) for every
        baseline (OGBench's own and the project's other baselines alike), and OGBench's
        per-dataset flags (``impls/hyperparameters.sh``) for its agents but GCBC: the maze's
        discount (giant 0.995) and, on stitch data, actor goals half random
        (``actor_p_randomgoal=0.5``); the alphas of the point mazes are the agents' defaults."""
        fields = {"width": 512, "depth": 4, "batch_size": 1024}
        if name in OGBENCH_VALUE_AGENTS:
            fields["gamma"] = discount(self.maze)
            if self.recipe == "stitch":
                fields["actor_p_randomgoal"] = 0.5
        return fields

    def collect(self, key, config: Config, *, mesh: Mesh | None = None, progress: bool = True
                ) -> Transitions:
        c = config.collect
        steps = collect_steps(key, c, progress=progress)
        data, _ = relabel(seed_rng(jax.random.fold_in(key, 1)), steps, c.goals_per_transition,
                          c.p_curgoal, c.p_trajgoal, c.discount)
        return data.astype_canonical()

    def data_summary(self, data: Transitions, config: Config) -> dict:
        return {"rows": data.size, "successes": int(np.sum(np.asarray(data.done)))}

    def data_table(self, summaries: Sequence[dict]) -> dict:
        return {k: [s[k] for s in summaries] for k in ("rows", "successes")}

    def evaluate(self, act_of, policies, config: Config, seeds: Sequence[int], *,
                 quick: bool = False) -> Evaluation:
        cfg = config.eval
        program = _protocol(config.collect.maze, cfg)
        keys = jnp.stack([purpose_key(int(s) + cfg.seed, "eval") for s in seeds])
        rollouts = run_protocol(program, seed_acts(act_of), policies, keys)
        per_seed = []
        for i, seed in enumerate(seeds):
            one = jax.tree.map(lambda x, i=i: x[i], rollouts)
            per_seed.append({"seed": int(seed), "eval_seed": int(seed) + cfg.seed,
                             "tasks": summarize(one, cfg)})
        return Evaluation(per_seed, {"tasks": rollouts})

    def scripted(self, config: Config):
        """OGBench's data-collecting oracle without its noise, finishing on the goal: the unit
        direction to the BFS subgoal cell's centre, or to the goal itself once in its cell (the
        cell centre can be 1.4 from a noisy goal).  An upper reference, not a learner."""
        maze = config.collect.maze
        return lambda key, s, g: host_call(functools.partial(oracle_action, get_maze(maze)), s, g)

    def seed_rates(self, result: dict) -> dict:
        r = result["tasks"]
        rates = {"success_rate": r["success_rate"], "idle_fraction": r["idle_fraction"]}
        rates.update({f"task{row['task']}": row["success_rate"] for row in r["per_task"]})
        return rates

    def figures(self, out_dir: Path, result: dict, rollouts: dict, config: Config,
                value_fn: Callable | None = None) -> list[Path]:
        out_dir.mkdir(parents=True, exist_ok=True)
        maze = get_maze(config.collect.maze)
        paths = [plots.rollouts_figure(maze, rollouts["tasks"], result, out_dir / "maze_rollouts.png")]
        if value_fn is not None:
            paths.append(plots.value_figure(maze, value_fn, out_dir / "maze_value.png"))
        return paths
