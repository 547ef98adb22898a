"""OGBench's ``cube-single-v0`` (Park et al. 2024, ``ogbench/manipspace/envs/cube_env.py``), many
episodes side by side on the host.

The env is OGBench's own class (the pip package; nothing is downloaded): a UR5e arm with a Robotiq
2F-85 gripper and one 4 cm cube, native MuJoCo at 0.002 s, 25 substeps a control step (0.05 s),
and OGBench's Python differential-IK controller turning the 5-D action (effector move x, y, z
times 0.05 m, yaw times 0.3 rad, gripper opening change) into joint targets.  Observation 28-D:
joint positions (6) and velocities (6), ``(effector - [0.425, 0, 0]) x 10`` (3), effector yaw
cos, sin, gripper opening x 3, gripper contact, ``(cube - [0.425, 0, 0]) x 10`` (3), cube
quaternion (4), cube yaw cos, sin (:data:`OBS` names the slices).

Batching.  Building one env compiles its MJCF scene (0.6-1.6 s here), so a batch does not hold
one env per episode: it holds one ``MjData`` per episode and a few env objects (``workers``), and
steps an episode by pointing a worker's env at that episode's ``MjData`` and random generator
(``env._data``, ``env._np_random``) and calling OGBench's own ``step`` (or ``reset``,
``set_new_target``).  Everything an episode carries from step to step lives there: the physics
state (``qpos, qvel``, the cube's target in ``mocap_pos``, the solver's warm start, ``time``)
and the env's random stream; the Python attributes ``step`` reads (``_success``, ``_prev_qpos``,
``_target_effector_pose``) are recomputed by every step before they are read, and the IK
controller starts every solve from the current joints.  So an episode's steps are a dedicated
OGBench env's, whatever the batch and the worker (tests/test_cube.py: equal to 1e-9 in
observation units; the rounding-level gap, 1e-17 to 1e-14, comes from OGBench's unseeded goal
settling below).

One change to OGBench's env: ``reset`` in task mode settles the goal scene with two random
actions from ``self.action_space.sample()``, a fresh, unseeded ``Box`` on every access, so
OGBench's goal observations are not reproducible.  :class:`SeededCubeEnv` draws them from a
``Box`` seeded with the episode's seed instead (the same uniform distribution).  Only the
goal's arm part depends on them (the arm starts 0.2-0.35 m high and moves at most 0.1 m: it
cannot touch the cube), which success never reads.

Threads: MuJoCo's ``mj_step`` releases the GIL, the IK controller's NumPy does not; measured
speeds (``docs/cube.md``): see :func:`step_rate`.
"""

from __future__ import annotations

import contextlib
import functools
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, Sequence

import gymnasium
import mujoco
import numpy as np
from ogbench.manipspace.envs.cube_env import CubeEnv

ENV_ID = "cube-single-v0"
OBS_DIM = 28
ACTION_DIM = 5
N_TASKS = 5
GOAL_TOL = 0.04  # success: the cube within 0.04 m of its target (orientation ignored)
XYZ_CENTER = np.array([0.425, 0.0, 0.0])
XYZ_SCALE = 10.0
GRIPPER_SCALE = 3.0
# The observation's parts (CubeEnv.compute_observation, one cube).
OBS = {"joint_pos": slice(0, 6), "joint_vel": slice(6, 12), "effector_pos": slice(12, 15),
       "effector_yaw": slice(15, 17), "gripper_opening": slice(17, 18),
       "gripper_contact": slice(18, 19), "cube_pos": slice(19, 22), "cube_quat": slice(22, 26),
       "cube_yaw": slice(26, 28)}
TASK_NAMES = ("task1_horizontal", "task2_vertical1", "task3_vertical2", "task4_diagonal1",
              "task5_diagonal2")


def cube_position(obs) -> np.ndarray:
    """The cube's world position ``[..., 3]`` (metres) from observations ``[..., 28]``."""
    return np.asarray(obs, np.float64)[..., OBS["cube_pos"]] / XYZ_SCALE + XYZ_CENTER


def effector_position(obs) -> np.ndarray:
    """The effector's (pinch site's) world position ``[..., 3]`` from observations."""
    return np.asarray(obs, np.float64)[..., OBS["effector_pos"]] / XYZ_SCALE + XYZ_CENTER


class SeededCubeEnv(CubeEnv):
    """OGBench's ``CubeEnv`` whose ``action_space`` is one ``Box`` seeded by :meth:`seed_space`
    (OGBench's returns a fresh unseeded ``Box`` on every access; module docstring)."""

    def __init__(self, *args, **kwargs):
        self._space = gymnasium.spaces.Box(-1.0, 1.0, (ACTION_DIM,), np.float32)
        super().__init__(*args, **kwargs)

    @property
    def action_space(self):
        return self._space

    def seed_space(self, seed: int) -> None:
        self._space.seed(int(seed))


def make_env(mode: str = "task") -> SeededCubeEnv:
    """One ``cube-single-v0`` env as ``gymnasium.make`` builds it (``CubeEnv(env_type="single")``;
    unwrapped: the batch counts steps itself), reset once so that its model is compiled.
    ``mode``: ``"task"`` (evaluation; termination is the caller's) or ``"data_collection"``
    (random scenes and targets, ``terminate_at_goal=False``: OGBench's data script)."""
    if mode not in ("task", "data_collection"):
        raise ValueError(f"mode must be 'task' or 'data_collection', got {mode!r}")
    env = SeededCubeEnv(env_type="single", mode=mode, terminate_at_goal=False)
    env.seed_space(0)
    env.reset(seed=0, options={"task_id": 1} if mode == "task" else None)
    return env


@functools.lru_cache(maxsize=8)
def _worker_env(mode: str, worker: int) -> SeededCubeEnv:
    return make_env(mode)


def worker_envs(mode: str, workers: int) -> list[SeededCubeEnv]:
    """``workers`` env objects of ``mode``, built once per process and reused by every batch."""
    return [_worker_env(mode, w) for w in range(workers)]


class EpisodeBatch:
    """``n`` episodes of ``cube-single-v0`` held on the host (module docstring): one ``MjData``
    and one random generator each, stepped by ``workers`` env objects (threads when more than
    one).  Not thread-safe itself: one caller at a time."""

    def __init__(self, n: int, mode: str = "task", workers: int = 1):
        if not (isinstance(n, int) and n >= 1 and isinstance(workers, int) and workers >= 1):
            raise ValueError(f"EpisodeBatch needs n >= 1 episodes and workers >= 1, got {n}, {workers}")
        self.n, self.mode = n, mode
        self.envs = worker_envs(mode, min(workers, n))
        model = self.envs[0].model
        self.datas = [mujoco.MjData(model) for _ in range(n)]
        self.rngs: list[np.random.Generator | None] = [None] * n
        # contiguous chunks: worker w steps episodes chunks[w]
        self.chunks = np.array_split(np.arange(n), len(self.envs))
        self._pool = ThreadPoolExecutor(len(self.envs)) if len(self.envs) > 1 else None

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown()

    @contextlib.contextmanager
    def episode(self, env: SeededCubeEnv, i: int):
        """``env`` pointed at episode ``i`` (its ``MjData`` and random generator)."""
        env._data = self.datas[i]
        env._np_random = self.rngs[i]
        try:
            yield env
        finally:
            self.rngs[i] = env._np_random

    def map(self, fn: Callable[[SeededCubeEnv, int], object], episodes: Sequence[int] | None = None
            ) -> list:
        """``[fn(env, i) for i in episodes]`` (all by default), each call with ``env`` pointed at
        episode ``i``; the workers' chunks in threads.  Results in the order of ``episodes``."""
        chosen = np.arange(self.n) if episodes is None else np.asarray(episodes, np.int64)
        want = np.zeros(self.n, bool)
        want[chosen] = True

        def run(w: int) -> dict:
            env, out = self.envs[w], {}
            for i in self.chunks[w]:
                if want[i]:
                    with self.episode(env, int(i)) as e:
                        out[int(i)] = fn(e, int(i))
            return out

        if self._pool is None:
            parts = [run(0)]
        else:
            parts = list(self._pool.map(run, range(len(self.envs))))
        merged = {k: v for p in parts for k, v in p.items()}
        return [merged[int(i)] for i in chosen]

    def reset(self, seeds: Sequence[int], task_ids: Sequence[int] | None = None) -> tuple:
        """Reset every episode: ``env.reset(seed=seeds[i], options={"task_id": task_ids[i]})``
        (task mode; the goal-settling actions seeded by ``seeds[i]`` too).  Returns the
        observations ``[n, 28]`` and the reset infos (a list; task mode: ``info["goal"]`` is the
        goal observation)."""
        if len(seeds) != self.n or (task_ids is not None and len(task_ids) != self.n):
            raise ValueError(f"reset needs {self.n} seeds (and task ids), got {len(seeds)}")
        if self.mode == "task" and task_ids is None:
            raise ValueError("task mode resets need task_ids (1-5)")

        def one(env: SeededCubeEnv, i: int):
            env.seed_space(int(seeds[i]))
            options = None if task_ids is None else {"task_id": int(task_ids[i])}
            return env.reset(seed=int(seeds[i]), options=options)

        out = self.map(one)
        return np.stack([o for o, _ in out]), [info for _, info in out]

    def step(self, actions: np.ndarray, live: np.ndarray | None = None) -> tuple:
        """One step of the ``live`` episodes (all by default) with ``actions [n, 5]`` (clipped to
        ``[-1, 1]``, as OGBench's evaluation and data script do).  Returns the observations
        ``[n, 28]`` (NaN for episodes not stepped), ``info["success"] [n]`` and the step infos
        (None for episodes not stepped)."""
        a = np.clip(np.asarray(actions, np.float64).reshape(self.n, ACTION_DIM), -1.0, 1.0)
        chosen = np.arange(self.n) if live is None else np.nonzero(np.asarray(live, bool))[0]
        out = self.map(lambda env, i: env.step(a[i]), chosen)
        obs = np.full((self.n, OBS_DIM), np.nan)
        success = np.zeros(self.n, bool)
        infos: list = [None] * self.n
        for i, (ob, _, _, _, info) in zip(chosen, out):
            obs[i], success[i], infos[i] = ob, bool(info["success"]), info
        return obs, success, infos
