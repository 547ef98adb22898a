"""OGBench's pointmaze (Park et al. 2024, ``ogbench/locomaze/point.py`` and ``maze.py``): the maze,
its oracle subgoals and the point's physics, stepped natively in batches.

The scene is OGBench's own MuJoCo model (built by the ``ogbench`` package at run time; nothing is
downloaded): a sphere of radius 0.7 on two slide joints, the walls 4 x 4 boxes at ``xy = (4 j - 4,
4 i - 4)`` for every 1 in the maze map.  A step is OGBench's ``PointEnv.step``: ``qpos += 0.2 a``,
``qvel = 0``, then 5 RK4 steps of 0.02 s whose wall contacts push the point out.  Here the actions
are clipped to ``[-1, 1]^2`` first (OGBench's data generation and evaluation clip them; the env
itself does not).  :meth:`Maze.step` runs a batch of points with ``mujoco.rollout`` (native,
threaded): positions equal OGBench's gymnasium env to 1e-5 in float64 (tests/test_pointmaze.py;
0 difference seen: each batch starts the contact solver cold where the env warm-starts it, so
agreement is only guaranteed to the solver's tolerance).
Measured here (2 cores): ~21,000 env steps/s for a batch of 250 or 1000 (MJX matched the env to
2e-6 in float32 but ran ~900/s for a batch of 1024 on these cores: shared/DESIGN.md §8).

Teleport (OGBench's ``pointmaze-teleport``): after a step that ends within 1.5 of an inbound
teleporter's centre the point is moved to one of the three outbound ones, uniformly at random
(``MazeEnv.step``).  The observation returned by that step is the position *before* the move
(success is also checked there); the next step starts from the outbound teleporter.  So a
rollout carries the observed position and whether a move is pending (:meth:`Maze.teleport`).
The oracle's BFS ignores the teleporters, as OGBench's does.

Cells ``(i, j)``: row ``i`` (y), column ``j`` (x); ``xy_to_ij`` and ``ij_to_xy`` as OGBench's.
The oracle subgoal (``get_oracle_subgoal``): the neighbouring free cell of least BFS distance to
the goal's cell, strictly less than the current cell's (else the current cell), neighbours tried in
the order up, left, down, right.
"""

from __future__ import annotations

import functools
import os
import threading

import mujoco
import numpy as np
import ogbench
from mujoco import rollout

MAZES = ("medium", "large", "giant", "teleport")
MAZE_UNIT = 4.0
OFFSET = 4.0  # ogbench: _offset_x = _offset_y = 4
STEP_SCALE = 0.2  # qpos += 0.2 a
FRAME_SKIP = 5
GOAL_TOL = 1.0  # success: |xy - goal| <= 1 (point mazes)
NOISE = 1.0  # start / goal noise: uniform +-1 per coordinate (noise 1 x maze_unit / 4)
_NEIGHBOURS = ((-1, 0), (0, -1), (1, 0), (0, 1))
TELEPORT_REACH = 1.5  # a step ending within 1.5 x teleport_radius (1) of an inbound centre teleports


def env_name(maze: str) -> str:
    """OGBench's dataset/environment name of ``maze``'s navigate task."""
    return f"pointmaze-{maze}-navigate-v0"


class Maze:
    """One maze: map, cells, BFS tables, evaluation tasks and the native batched step.

    Thread-safe: every :meth:`step` uses its own ``MjData`` pool under a lock."""

    def __init__(self, maze: str = "medium"):
        if maze not in MAZES:
            raise ValueError(f"unknown maze {maze!r}; OGBench's point mazes: {', '.join(MAZES)}")
        env = ogbench.make_env_and_datasets(env_name(maze), env_only=True)
        u = env.unwrapped
        self.name = maze
        self.model: mujoco.MjModel = u.model
        self.map = np.asarray(u.maze_map, np.int64)
        self.tasks = [(tuple(t["init_ij"]), tuple(t["goal_ij"])) for t in u.task_infos]
        info = u._teleport_info  # None but in the teleport maze
        self.teleport_in = (np.zeros((0, 2)) if info is None else
                            np.asarray(info["teleport_in_xys"], np.float64))
        self.teleport_out = (np.zeros((0, 2)) if info is None else
                             np.asarray(info["teleport_out_xys"], np.float64))
        self.teleport_reach = 0.0 if info is None else TELEPORT_REACH * info["teleport_radius"]
        env.close()
        rows, cols = self.map.shape
        self.free = [(i, j) for i in range(rows) for j in range(cols) if self.map[i, j] == 0]
        self.vertex = [(i, j) for (i, j) in self.free if not self._corridor(i, j)]
        self.dist = self._bfs_tables()  # [rows, cols (goal), rows, cols (cell)], -1: unreachable
        self.next_cell = self._next_cells()  # [rows, cols (goal), rows, cols (cell), 2]
        self._lock = threading.Lock()
        threads = max(1, min(os.cpu_count() or 1, 16))
        self._datas = [mujoco.MjData(self.model) for _ in range(threads)]

    # --- geometry
    def _corridor(self, i: int, j: int) -> bool:
        m = self.map
        vertical = m[i - 1, j] == 0 and m[i + 1, j] == 0 and m[i, j - 1] == 1 and m[i, j + 1] == 1
        horizontal = m[i, j - 1] == 0 and m[i, j + 1] == 0 and m[i - 1, j] == 1 and m[i + 1, j] == 1
        return bool(vertical or horizontal)

    @staticmethod
    def ij_to_xy(ij) -> np.ndarray:
        """Cell centres: ``x = 4 j - 4``, ``y = 4 i - 4`` (``ij [..., 2]``)."""
        ij = np.asarray(ij, np.float64)
        return np.stack([ij[..., 1] * MAZE_UNIT - OFFSET, ij[..., 0] * MAZE_UNIT - OFFSET], -1)

    @staticmethod
    def xy_to_ij(xy) -> np.ndarray:
        """The cell of ``xy [..., 2]`` (OGBench's ``int((y + 4 + 2) / 4)``: truncation)."""
        xy = np.asarray(xy, np.float64)
        i = np.trunc((xy[..., 1] + OFFSET + 0.5 * MAZE_UNIT) / MAZE_UNIT).astype(np.int64)
        j = np.trunc((xy[..., 0] + OFFSET + 0.5 * MAZE_UNIT) / MAZE_UNIT).astype(np.int64)
        return np.stack([i, j], -1)

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """``(x_min, y_min, x_max, y_max)`` of the free cells' squares."""
        xy = self.ij_to_xy(np.asarray(self.free))
        h = MAZE_UNIT / 2
        return (float(xy[:, 0].min() - h), float(xy[:, 1].min() - h), float(xy[:, 0].max() + h),
                float(xy[:, 1].max() + h))

    def _bfs_tables(self) -> np.ndarray:
        rows, cols = self.map.shape
        dist = np.full((rows, cols, rows, cols), -1, np.int64)
        for gi, gj in self.free:
            d = dist[gi, gj]
            d[gi, gj] = 0
            queue = [(gi, gj)]
            while queue:
                i, j = queue.pop(0)
                for di, dj in _NEIGHBOURS:
                    ni, nj = i + di, j + dj
                    if 0 <= ni < rows and 0 <= nj < cols and self.map[ni, nj] == 0 and d[ni, nj] == -1:
                        d[ni, nj] = d[i, j] + 1
                        queue.append((ni, nj))
        return dist

    def _next_cells(self) -> np.ndarray:
        rows, cols = self.map.shape
        nxt = np.zeros((rows, cols, rows, cols, 2), np.int64)
        for gi in range(rows):
            for gj in range(cols):
                d = self.dist[gi, gj]
                for i in range(rows):
                    for j in range(cols):
                        best = (i, j)
                        for di, dj in _NEIGHBOURS:
                            ni, nj = i + di, j + dj
                            if (0 <= ni < rows and 0 <= nj < cols and self.map[ni, nj] == 0
                                    and d[ni, nj] < d[best]):
                                best = (ni, nj)
                        nxt[gi, gj, i, j] = best
        return nxt

    def subgoal_direction(self, xy: np.ndarray, goal_xy: np.ndarray) -> np.ndarray:
        """The unit direction ``[B, 2]`` from ``xy`` to the centre of the oracle subgoal cell
        towards ``goal_xy`` (OGBench's navigate data: ``d / (|d| + 1e-6)``)."""
        c, gc = self.xy_to_ij(xy), self.xy_to_ij(goal_xy)
        sub = self.next_cell[gc[:, 0], gc[:, 1], c[:, 0], c[:, 1]]
        d = self.ij_to_xy(sub) - xy
        return d / (np.linalg.norm(d, axis=-1, keepdims=True) + 1e-6)

    def path_length(self, xy: np.ndarray, goal_xy: np.ndarray) -> np.ndarray:
        """BFS cells between the cells of ``xy`` and ``goal_xy`` ([B]; -1: unreachable)."""
        c, gc = self.xy_to_ij(xy), self.xy_to_ij(goal_xy)
        return self.dist[gc[:, 0], gc[:, 1], c[:, 0], c[:, 1]]

    def noisy(self, rng: np.random.Generator, ij) -> np.ndarray:
        """Cell centres with OGBench's noise: uniform ``+-1`` per coordinate (``[B, 2]``)."""
        xy = self.ij_to_xy(ij)
        return xy + rng.uniform(-NOISE, NOISE, xy.shape)

    # --- teleporters
    @property
    def has_teleports(self) -> bool:
        return len(self.teleport_in) > 0

    def teleport_pending(self, xy) -> np.ndarray:
        """Whether a step that ended at ``xy [..., 2]`` teleports the point (OGBench's check
        after the physics step; always False in mazes without teleporters)."""
        xy = np.asarray(xy, np.float64)
        if not self.has_teleports:
            return np.zeros(xy.shape[:-1], bool)
        d = np.linalg.norm(xy[..., None, :] - self.teleport_in, axis=-1)
        return (d <= self.teleport_reach).any(-1)

    def teleport(self, xy, pending, u) -> np.ndarray:
        """Where the next step starts: ``xy`` itself, or where ``pending`` the outbound
        teleporter ``floor(3 u)`` (``u [...]`` uniform in ``[0, 1)``: OGBench's
        ``np.random.randint(3)``)."""
        xy = np.asarray(xy, np.float64)
        if not self.has_teleports:
            return xy
        n = len(self.teleport_out)
        out = self.teleport_out[np.minimum((np.asarray(u) * n).astype(np.int64), n - 1)]
        return np.where(np.asarray(pending, bool)[..., None], out, xy)

    # --- physics
    def step(self, qpos: np.ndarray, action: np.ndarray) -> np.ndarray:
        """One env step of every point: ``qpos [..., 2]``, ``action [..., 2]`` (clipped to
        ``[-1, 1]``) -> new ``qpos`` (float64, the shape of ``qpos``)."""
        q = np.asarray(qpos, np.float64)
        a = np.clip(np.asarray(action, np.float64), -1.0, 1.0)
        shape = np.broadcast_shapes(q.shape, a.shape)
        q, a = np.broadcast_to(q, shape).reshape(-1, 2), np.broadcast_to(a, shape).reshape(-1, 2)
        if q.shape[0] == 0:
            return np.zeros(shape)
        state = np.zeros((q.shape[0], 5))  # FULLPHYSICS: time, qpos (2), qvel (2)
        state[:, 1:3] = q + STEP_SCALE * a
        control = np.zeros((q.shape[0], FRAME_SKIP, self.model.nu))
        with self._lock:
            out, _ = rollout.rollout(self.model, self._datas, state, control)
        return out[:, -1, 1:3].reshape(shape)


@functools.lru_cache(maxsize=4)
def get_maze(maze: str = "medium") -> Maze:
    """The :class:`Maze` of that name, built once per process."""
    return Maze(maze)
