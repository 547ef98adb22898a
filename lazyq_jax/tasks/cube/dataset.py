"""OGBench's ``cube-single-play-v0`` data: the play recipe, its ``.npz`` files, goals.

* :func:`play`: OGBench's ``data_gen_scripts/generate_manipspace.py --env_name=cube-single-v0
  --dataset_type=play`` (``commands.sh``: 1000 episodes x 1001 steps): ``cube-single-v0`` with
  ``mode="data_collection"`` and ``terminate_at_goal=False`` (a random arm pose, cube pose and
  target at reset), actions from OGBench's ``CubePlanOracle`` (a keyframe plan: above the cube,
  grasp, a clearance waypoint, place, a random final effector pose; temporally correlated noise
  ``noise x (0.05, 0.05, 0.05, 0.3, 1.0) x N(0, 1)`` smoothed over time by
  ``scipy.ndimage.gaussian_filter1d(sigma=noise_smoothing)`` is added to the *plan*, and each
  action is the normalised difference between the plan's next pose and the current one),
  clipped to ``[-1, 1]``; with ``p_random_action`` a uniform action instead; when the oracle's
  plan ends, ``env.set_new_target()`` draws a new target and the oracle plans again; the
  episode ends after ``steps`` steps (the script's ``TimeLimit``; ``terminals`` marks that
  step).  Stored as the script stores them: ``observations`` (the observation before each
  step), ``actions`` (clipped), ``terminals``, ``qpos``, ``qvel`` (``info["prev_qpos"]``,
  ``info["prev_qvel"]``: the physics state of that observation), float32 / bool.
  Episodes run side by side (:class:`~lazyq_jax.tasks.cube.env.EpisodeBatch`).  OGBench's
  oracle draws from the global ``np.random`` (the script draws ``np.random.rand()`` every step
  for ``p_random_action`` too): here each episode has its own ``RandomState`` that plays the
  global one's part (swapped in around the oracle's planning, under a lock), and the env its
  own seed, both drawn from the caller's ``Generator``.  So an episode is the script's episode
  for that seed and that global state, step for step (tests/test_cube.py), and the data do not
  depend on how episodes are batched.
* :func:`load_npz` / :func:`save_npz`: OGBench's files (pointmaze's reader, with the cube's
  shapes checked: observations 28 wide, actions 5).
* Transitions and goals: :func:`lazyq_jax.tasks.pointmaze.dataset.trajectory_transitions` and
  ``relabel`` (OGBench's ``GCDataset`` value goals; any state width) apply unchanged.
"""

from __future__ import annotations

import contextlib
import dataclasses
import multiprocessing
import threading
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from ogbench.manipspace.oracles.plan.cube_plan import CubePlanOracle
from tqdm.auto import tqdm

from lazyq_jax.data import DatasetError
from lazyq_jax.tasks.cube.env import ACTION_DIM, OBS_DIM, EpisodeBatch, SeededCubeEnv
from lazyq_jax.tasks.pointmaze.dataset import load_npz as _load_ogbench_npz
from lazyq_jax.tasks.pointmaze.dataset import save_npz

__all__ = ["load_npz", "make_oracle", "play", "play_seeded", "save_npz"]

NOISE_SCALE = np.array([0.05, 0.05, 0.05, 0.3, 1.0])  # PlanOracle.compute_plan's per-axis scale
_GLOBAL_RNG = threading.Lock()


@contextlib.contextmanager
def global_rng(state: np.random.RandomState):
    """``np.random``'s global functions drawing from ``state`` inside the block (then the caller's
    global state is back); one block at a time across threads."""
    with _GLOBAL_RNG:
        saved = np.random.get_state()
        np.random.set_state(state.get_state())
        try:
            yield
        finally:
            state.set_state(np.random.get_state())
            np.random.set_state(saved)


def make_oracle(env: SeededCubeEnv, noise: float = 0.1, noise_smoothing: float = 0.5) -> CubePlanOracle:
    """OGBench's play oracle as the data script builds it (``segment_dt`` 0.4 s, its default)."""
    return CubePlanOracle(env=env, noise=noise, noise_smoothing=noise_smoothing)


@dataclasses.dataclass
class _Episode:
    rs: np.random.RandomState  # plays np.random's global part for this episode
    oracle: CubePlanOracle
    ob: np.ndarray
    info: dict


def play(rng: np.random.Generator, episodes: int, steps: int = 1001, noise: float = 0.1,
         noise_smoothing: float = 0.5, p_random_action: float = 0.0, workers: int = 1,
         processes: int = 1, progress: bool = False) -> dict[str, np.ndarray]:
    """``episodes`` play episodes of ``steps`` env steps (module docstring), in OGBench's file
    format: ``observations [E * T, 28]``, ``actions [E * T, 5]``, ``qpos [E * T, 21]``, ``qvel
    [E * T, 20]`` (float32), ``terminals [E * T]`` (bool, the last step of each episode); also,
    for statistics, ``successes`` (the target cube within 0.04 m of its target after the step)
    and ``new_targets`` (the oracle's plan ended at that step and a new target was set).
    Each episode's two seeds (env, oracle) are drawn from ``rng`` first; the episodes are then
    stepped by ``workers`` threads in each of ``processes`` processes (spawned, a contiguous
    share of the episodes each): the data do not depend on either.  ``progress``: a bar over the
    steps (with several processes, the first's: they step their shares side by side)."""
    if not (isinstance(episodes, int) and episodes >= 1 and isinstance(steps, int) and steps >= 2):
        raise ValueError(f"play needs episodes >= 1 and steps >= 2, got {episodes}, {steps}")
    if not (isinstance(processes, int) and processes >= 1):
        raise ValueError(f"play needs processes >= 1, got {processes!r}")
    seeds = rng.integers(0, 2**31 - 1, size=(episodes, 2))
    args = (steps, noise, noise_smoothing, p_random_action, workers)
    if processes == 1 or episodes == 1:
        return play_seeded(seeds, *args, progress=progress)
    chunks = [c for c in np.array_split(seeds, processes) if len(c)]
    with ProcessPoolExecutor(len(chunks), mp_context=multiprocessing.get_context("spawn")) as pool:
        bars = [progress] + [False] * (len(chunks) - 1)
        parts = list(pool.map(play_seeded, chunks, *([a] * len(chunks) for a in args), bars))
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def play_seeded(seeds: np.ndarray, steps: int, noise: float, noise_smoothing: float,
                p_random_action: float, workers: int = 1, progress: bool = False) -> dict[str, np.ndarray]:
    """:func:`play`'s episodes for the seeds ``[E, 2]`` (env reset seed, oracle random state)."""
    episodes = len(seeds)
    batch = EpisodeBatch(episodes, "data_collection", workers=workers)
    try:
        obs0, infos = batch.reset([int(s) for s in seeds[:, 0]])
        eps = []
        for i in range(episodes):
            ep = _Episode(np.random.RandomState(int(seeds[i, 1])),
                          make_oracle(batch.envs[0], noise, noise_smoothing), obs0[i], infos[i])
            with global_rng(ep.rs):
                ep.oracle.reset(ep.ob, ep.info)
            eps.append(ep)
        nq, nv = batch.envs[0].model.nq, batch.envs[0].model.nv
        obs = np.zeros((episodes, steps, OBS_DIM), np.float32)
        acts = np.zeros((episodes, steps, ACTION_DIM), np.float32)
        qpos = np.zeros((episodes, steps, nq), np.float32)
        qvel = np.zeros((episodes, steps, nv), np.float32)
        successes = np.zeros((episodes, steps), bool)
        new_targets = np.zeros((episodes, steps), bool)

        def one(env: SeededCubeEnv, i: int, t: int) -> None:
            ep = eps[i]
            if ep.rs.rand() < p_random_action:  # the script draws np.random.rand() every step
                action = ep.rs.uniform(-1.0, 1.0, ACTION_DIM)
            else:
                action = np.array(ep.oracle.select_action(ep.ob, ep.info))
            action = np.clip(action, -1, 1)
            next_ob, _, _, _, info = env.step(action)
            if ep.oracle.done:  # a new target when the plan has ended (p_stack irrelevant: one cube)
                agent_ob, agent_info = env.set_new_target(p_stack=0.0)
                with global_rng(ep.rs):
                    ep.oracle.reset(agent_ob, agent_info)
                new_targets[i, t] = True
            obs[i, t], acts[i, t] = ep.ob, action
            qpos[i, t], qvel[i, t] = info["prev_qpos"], info["prev_qvel"]
            successes[i, t] = info["success"]
            ep.ob, ep.info = next_ob, info

        for t in tqdm(range(steps), desc="cube play data", disable=not progress, leave=False):
            batch.map(lambda env, i, t=t: one(env, i, t))
    finally:
        batch.close()
    terminals = np.zeros((episodes, steps), bool)
    terminals[:, -1] = True
    flat = lambda x: x.reshape(episodes * steps, *x.shape[2:])
    return {"observations": flat(obs), "actions": flat(acts), "terminals": flat(terminals),
            "qpos": flat(qpos), "qvel": flat(qvel), "successes": flat(successes),
            "new_targets": flat(new_targets)}


def load_npz(path: str | Path) -> dict[str, np.ndarray]:
    """An OGBench ``cube-single`` dataset file (e.g. OGBench's ``cube-single-play-v0.npz``):
    ``observations [M, 28]``, ``actions [M, 5]`` (float32), ``terminals [M]`` (bool);
    :class:`DatasetError` for another env's file or the checks of pointmaze's reader (missing
    keys, lengths, non-finite values, a last step that is not terminal)."""
    path = Path(path)
    if path.is_file():
        with np.load(path) as f:
            shapes = {k: f[k].shape for k in ("observations", "actions") if k in f.files}
        if shapes.get("observations", (0, OBS_DIM))[1:] != (OBS_DIM,) or \
                shapes.get("actions", (0, ACTION_DIM))[1:] != (ACTION_DIM,):
            raise DatasetError(f"{path}: observations {shapes.get('observations')} and actions "
                               f"{shapes.get('actions')}; cube-single's are [M, {OBS_DIM}] and "
                               f"[M, {ACTION_DIM}] (is it another env's file, e.g. cube-double's 37-D?)")
    return _load_ogbench_npz(path, obs_dim=None)
