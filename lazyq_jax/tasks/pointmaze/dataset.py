"""OGBench's pointmaze data: the navigate recipe, its ``.npz`` files, and goal relabelling.

* :func:`navigate`: OGBench's ``data_gen_scripts/generate_locomaze.py --dataset_type=navigate
  --noise=0.5`` (``commands.sh``): episodes of ``steps`` env steps (1001; no termination at the
  goal), the start uniform over the free cells and the goal over the non-corridor ("vertex")
  cells, both with the +-1 noise; action = the unit direction to the oracle subgoal plus
  ``N(0, noise)`` per component, clipped to ``[-1, 1]``; a new goal cell whenever the point is
  within 1.0 of the goal.  Episodes run side by side (one batched native step each step), seeded
  by a NumPy ``Generator``; the random stream is not OGBench's (which draws from the global
  ``np.random``), the distribution is.
* :func:`load_npz` / :func:`save_npz`: OGBench's dataset files (``observations``, ``actions``,
  ``terminals`` marking each trajectory's last step; ``qpos``, ``qvel`` kept when present).
* :func:`trajectory_transitions`: OGBench's ``load_dataset(compact_dataset=False)``: the
  transitions ``(s_t, a_t, s_{t+1})`` within each trajectory (its last observation has none) and
  each transition's trajectory end (the index of the trajectory's last transition).
* :func:`relabel`: goals as OGBench's ``GCDataset.sample_goals`` draws value goals (Park et al.
  2024, ``impls/utils/datasets.py``): the transition's own state with ``p_cur``, the state of a
  later transition of the same trajectory at a geometric offset (``p = 1 - discount``, clipped to
  the trajectory's last transition) with ``p_traj``, a uniformly random transition's state with
  ``p_rand``; ``success = (goal index == index)``, ``r = success - 1``, ``done = success``.
  OGBench draws fresh goals for every minibatch; lazy Q's neighbourhoods need a fixed dataset,
  so lazy Q trains on ``goals_per_transition`` relabelled copies of each transition; the
  rows keep their trajectory (``Transitions.traj_last``), and OGBench's agents draw fresh
  value and actor goals from the same trajectories every minibatch, as OGBench does
  (:mod:`lazyq_jax.agents.goals`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from lazyq_jax.data import DatasetError
from lazyq_jax.tasks.pointmaze.maze import GOAL_TOL, Maze
from lazyq_jax.types import Transitions

NPZ_KEYS = ("observations", "actions", "terminals")
STITCH_CELLS = 4  # a stitch episode's goal: a cell exactly this many BFS moves from the start
RECIPES = ("navigate", "stitch")


def navigate(maze: Maze, rng: np.random.Generator, episodes: int, steps: int = 1001,
             noise: float = 0.5, progress: bool = False) -> dict[str, np.ndarray]:
    """``episodes`` navigate episodes of ``steps`` env steps (module docstring), in OGBench's
    file format (:func:`run_episodes`)."""
    free, vertex = np.asarray(maze.free), np.asarray(maze.vertex)
    xy = maze.noisy(rng, free[rng.integers(len(free), size=episodes)])
    goal = maze.noisy(rng, vertex[rng.integers(len(vertex), size=episodes)])
    return run_episodes(maze, rng, xy, goal, steps, noise, new_goals=vertex, progress=progress,
                        desc="navigate data")


def cells_at(maze: Maze, steps: int = STITCH_CELLS) -> list[np.ndarray]:
    """For every free cell (in ``maze.free``'s order), the cells exactly ``steps`` BFS moves
    away (``[m, 2]``, possibly none)."""
    return [np.argwhere(maze.dist[i, j] == steps) for i, j in maze.free]


def stitch(maze: Maze, rng: np.random.Generator, episodes: int, steps: int = 201,
           noise: float = 0.5, progress: bool = False) -> dict[str, np.ndarray]:
    """``episodes`` stitch episodes of ``steps`` env steps (module docstring): the start
    uniform over the free cells, the goal uniform over the cells exactly 4 BFS moves from it
    (the start's own cell where there are none), both with the +-1 noise; the goal is kept
    after it is reached.  OGBench's file format (:func:`run_episodes`)."""
    free = np.asarray(maze.free)
    around = cells_at(maze)
    start = rng.integers(len(free), size=episodes)
    goal_cells = np.array([around[c][rng.integers(len(around[c]))] if len(around[c]) else free[c]
                           for c in start]).reshape(episodes, 2)
    xy = maze.noisy(rng, free[start])
    goal = maze.noisy(rng, goal_cells)
    return run_episodes(maze, rng, xy, goal, steps, noise, new_goals=None, progress=progress,
                        desc="stitch data")


def run_episodes(maze: Maze, rng: np.random.Generator, xy: np.ndarray, goal: np.ndarray,
                 steps: int, noise: float, new_goals: np.ndarray | None, progress: bool = False,
                 desc: str = "episodes") -> dict[str, np.ndarray]:
    """Episodes of ``steps`` env steps from ``xy [E, 2]`` towards ``goal [E, 2]``, side by
    side (one batched native step a step): action = the unit direction to the oracle subgoal
    plus ``N(0, noise)`` per component, clipped to ``[-1, 1]``; with ``new_goals`` (cells) a new
    noisy goal among them whenever the point is within 1.0 of the goal (navigate), else the
    goal stays (stitch).  In a maze with teleporters the observation after a step is the
    position before any teleport, the next step starts after it (:class:`Maze`), and the
    oracle reads the position the point is at, as OGBench's script does.

    Returns OGBench's file format: ``observations, actions, qpos [E * steps, 2]`` (float32;
    ``qpos``: where each step started, which differs from the observation after a
    teleport), ``terminals`` (bool, the last step of each episode); also ``goals`` (the goal
    being pursued) and ``successes`` (reached after the step), for statistics.  OGBench's
    files also hold ``qvel`` (the velocity left by the previous step's contacts); nothing
    here reads it, so it is not made."""
    episodes = len(xy)
    seen = xy  # the observation; xy: where the point is (they differ after a teleport)
    obs = np.zeros((episodes, steps, 2))
    acts, goals, qpos = np.zeros_like(obs), np.zeros_like(obs), np.zeros_like(obs)
    successes = np.zeros((episodes, steps), bool)
    for t in tqdm(range(steps), desc=desc, disable=not progress, leave=False):
        a = np.clip(maze.subgoal_direction(xy, goal) + rng.normal(0.0, noise, xy.shape), -1.0, 1.0)
        obs[:, t], acts[:, t], goals[:, t], qpos[:, t] = seen, a, goal, xy
        seen = xy = maze.step(xy, a)
        reached = np.linalg.norm(xy - goal, axis=-1) <= GOAL_TOL
        successes[:, t] = reached
        if new_goals is not None and reached.any():
            cells = new_goals[rng.integers(len(new_goals), size=int(reached.sum()))]
            goal[reached] = maze.noisy(rng, cells)
        if maze.has_teleports:
            xy = maze.teleport(xy, maze.teleport_pending(xy), rng.random(episodes))
    terminals = np.zeros((episodes, steps), bool)
    terminals[:, -1] = True
    flat = lambda x: x.reshape(episodes * steps, *x.shape[2:])
    f32 = lambda x: flat(x).astype(np.float32)
    return {"observations": f32(obs), "actions": f32(acts), "terminals": flat(terminals),
            "qpos": f32(qpos), "goals": f32(goals), "successes": flat(successes)}


def save_npz(path: str | Path, dataset: dict[str, np.ndarray]) -> Path:
    """``dataset``'s OGBench keys (and ``qpos``, ``qvel``) as a compressed ``.npz``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    keep = {k: dataset[k] for k in (*NPZ_KEYS, "qpos", "qvel") if k in dataset}
    np.savez_compressed(path, **keep)
    return path


def load_npz(path: str | Path, obs_dim: int | None = 2) -> dict[str, np.ndarray]:
    """An OGBench dataset file: ``observations [M, d]``, ``actions [M, n_a]`` (float32),
    ``terminals [M]`` (bool).  :class:`DatasetError` saying what is wrong for a missing file or
    key, mismatched lengths, non-finite values, observations of another width than
    ``obs_dim`` (pointmaze: the point's ``(x, y)``) or a last step that is not terminal."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"no dataset file at {path} (an OGBench .npz with {', '.join(NPZ_KEYS)})")
    with np.load(path) as f:
        missing = [k for k in NPZ_KEYS if k not in f.files]
        if missing:
            raise DatasetError(f"{path} lacks {missing}; an OGBench dataset has {list(NPZ_KEYS)} "
                               f"(found {f.files})")
        obs, acts, term = (np.asarray(f[k]) for k in NPZ_KEYS)
    if obs.ndim != 2 or acts.ndim != 2 or term.ndim != 1 or not len(obs) == len(acts) == len(term):
        raise DatasetError(f"{path}: need observations [M, d], actions [M, n_a], terminals [M]; "
                           f"got {obs.shape}, {acts.shape}, {term.shape}")
    if obs_dim is not None and obs.shape[1] != obs_dim:
        raise DatasetError(f"{path}: observations have {obs.shape[1]} columns, this task's states "
                           f"have {obs_dim} (pointmaze: the point's x, y); is it another env's file?")
    if len(obs) < 2 or not term[-1]:
        raise DatasetError(f"{path}: the last step must be terminal (terminals marks the last step "
                           "of every trajectory)")
    if not (np.all(np.isfinite(obs)) and np.all(np.isfinite(acts))):
        raise DatasetError(f"{path}: observations or actions are not all finite")
    return {"observations": obs.astype(np.float32), "actions": acts.astype(np.float32),
            "terminals": term.astype(bool)}


def trajectory_transitions(dataset: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """OGBench's non-compact transitions: ``s, a, s_next`` for every step but each
    trajectory's last, and ``last [N]``: the index of the last transition of each
    transition's trajectory (one-step trajectories have none and are dropped)."""
    obs, acts, term = dataset["observations"], dataset["actions"], np.asarray(dataset["terminals"], bool)
    keep = ~term  # a terminal step's next observation belongs to the next trajectory
    idx = np.nonzero(keep)[0]
    s, a, s_next = obs[idx], acts[idx], obs[idx + 1]
    ends = np.nonzero(term[idx + 1])[0]  # kept rows whose next step ends the trajectory
    last = ends[np.searchsorted(ends, np.arange(len(idx)))]
    return {"s": s, "a": a, "s_next": s_next, "last": last}


def relabel(rng: np.random.Generator, steps: dict[str, np.ndarray], goals_per_transition: int,
            p_cur: float = 0.2, p_traj: float = 0.5, discount: float = 0.99
            ) -> tuple[Transitions, np.ndarray]:
    """``goals_per_transition`` relabelled copies of every transition (module docstring;
    ``p_rand = 1 - p_cur - p_traj``) as :class:`Transitions` with vector goals ``g [N, 2]``,
    and the kind of each row's goal (0 current, 1 trajectory, 2 random) for statistics.
    The draw follows ``GCDataset.sample_goals``: trajectory goal with probability
    ``p_traj / (1 - p_cur)`` else random, then the current state with ``p_cur``."""
    s, last = steps["s"], steps["last"]
    n = len(s)
    idx = np.tile(np.arange(n), goals_per_transition)
    m = len(idx)
    offsets = rng.geometric(1.0 - discount, size=m)
    traj = np.minimum(idx + offsets, last[idx])
    rand = rng.integers(n, size=m)
    p_t = p_traj / (1.0 - p_cur) if p_cur < 1.0 else 0.0
    use_traj = rng.random(m) < p_t
    goal_idx = np.where(use_traj, traj, rand)
    use_cur = rng.random(m) < p_cur
    goal_idx = np.where(use_cur, idx, goal_idx)
    kind = np.where(use_cur, 0, np.where(use_traj, 1, 2)).astype(np.int8)
    success = goal_idx == idx
    copy = np.repeat(np.arange(goals_per_transition), n) * n  # each copy keeps its trajectories
    data = Transitions(s=s[idx], a=steps["a"][idx], s_next=steps["s_next"][idx],
                       r=success.astype(np.float32) - 1.0, g=s[goal_idx], done=success,
                       traj_last=(copy + last[idx]).astype(np.int32))
    return data, kind
