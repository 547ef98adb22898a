"""OGBench's ``cube-single-play-v0`` (Park et al. 2024): a UR5e arm with a Robotiq gripper moves
one cube to a target; a public manipulation benchmark nobody here built.

State: OGBench's 28-D observation (:data:`~lazyq_jax.tasks.cube.env.OBS`); action: the box
``[-1, 1]^5`` (effector move, yaw, gripper; OGBench's IK controller turns it into joint targets);
goal: a 28-D goal observation (``collect.goal_rep="observation"``, OGBench's benchmark) or the
goal's cube position (``"cube"``, OGBench's oracle representation); reward ``success - 1`` with
success the goal index equal to the transition's (OGBench's ``GCDataset``), discount 0.99.  Data:
OGBench's play recipe (or a user's OGBench ``.npz``, ``collect.dataset``) relabelled with
OGBench's value goals; evaluation: OGBench's five tasks, 50 episodes each of at most 200 steps,
success the cube within 0.04 m of its target.  See :mod:`~lazyq_jax.tasks.cube.env` (the env,
batched on the host), :mod:`~lazyq_jax.tasks.cube.dataset` (the data), docs/cube.md (what was
checked against OGBench's code, speeds) and shared/DESIGN.md §9.

Evaluation runs on the host, not through :func:`~lazyq_jax.tasks.base.run_protocol`: the env's
state is MuJoCo data and a Python IK controller that live on the host, so a jitted protocol
could only hold handles to them, stepped by a side-effecting callback (``jax.pure_callback``
promises JAX a pure function; pointmaze's step is one, this one is not).  The loop here does
what ``run_protocol`` does (the method's jitted ``act`` over all seeds' episodes at once every
step, stopping when all have ended) and steps only the episodes still running.
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
from lazyq_jax.config import Config
from lazyq_jax.keys import purpose_key
from lazyq_jax.tasks.base import CORRECT, NOT_PUSHED, Evaluation, Rollouts, Task, seed_acts
from lazyq_jax.tasks.cube import plots
from lazyq_jax.tasks.cube.config import CubeCollectConfig, CubeEvalConfig, check, presets
from lazyq_jax.tasks.cube.dataset import load_npz, play, save_npz
from lazyq_jax.tasks.cube.env import (ACTION_DIM, N_TASKS, OBS, OBS_DIM, EpisodeBatch, cube_position,
                                      effector_position)
from lazyq_jax.tasks.pointmaze.dataset import relabel, trajectory_transitions
from lazyq_jax.types import Transitions

__all__ = ["CubeCollectConfig", "CubeEvalConfig", "CubeTask", "cube_features", "evaluate_episodes",
           "goal_features", "goal_of", "load_npz", "play", "play_data", "save_npz"]

# How the play data are stepped (docs/cube.md, "Speed"): threads did not help on 2 cores (the IK
# controller holds the GIL); two spawned processes did, once their start (~5 s) is small.
COLLECT_PROCESSES = 2
PROCESSES_FROM_STEPS = 100_000  # fewer env steps: one process


def seed_rng(key: jax.Array) -> np.random.Generator:
    """A NumPy generator seeded from a JAX key (the host-side draws of one seed)."""
    return np.random.default_rng(int(jax.random.randint(key, (), 0, 2**31 - 1)))


def cube_features(s):
    """The ``"cube"`` feature map: ``phi(s) = (effector position (3), gripper opening (1), cube
    position (3))`` ``[..., 7]`` of observations ``s [..., 28]``, in the observation's units
    (positions ``(p - [0.425, 0, 0]) x 10``, the opening ``x 3``).  Jittable."""
    return jnp.concatenate([s[..., OBS["effector_pos"]], s[..., OBS["gripper_opening"]],
                            s[..., OBS["cube_pos"]]], -1)


def goal_features(g):
    """What of a goal observation ``g [..., 28]`` success reads: its cube position ``[..., 3]``
    (observation units; equal to OGBench's oracle goal representation ``compute_oracle_observation``).
    The goal side of :func:`cube_features`: lazy Q's neighbourhoods compare goal observations
    by it (``Problem.goal_features``; with ``collect.goal_rep="cube"`` the goals are these
    already)."""
    return g[..., OBS["cube_pos"]]


def goal_of(goal_obs: np.ndarray, goal_rep: str) -> np.ndarray:
    """The agent's goal from OGBench's goal observations ``[..., 28]`` (float32)."""
    g = np.asarray(goal_obs, np.float32)
    return g if goal_rep == "observation" else np.asarray(goal_features(g), np.float32)


@functools.lru_cache(maxsize=2)
def _shared_play(episodes: int, steps: int, noise: float, smoothing: float, p_random: float,
                 data_seed: int) -> dict:
    return play(np.random.default_rng(data_seed), episodes, steps, noise, smoothing, p_random,
                processes=_processes(episodes, steps))


def _processes(episodes: int, steps: int) -> int:
    return COLLECT_PROCESSES if episodes * steps >= PROCESSES_FROM_STEPS else 1


def play_data(key: jax.Array, c: CubeCollectConfig, progress: bool = False) -> dict:
    """One seed's trajectories in OGBench's format: the file ``c.dataset`` if set, the play
    data of ``c.data_seed`` if set (generated once per process), else drawn from ``key``."""
    if c.dataset is not None:
        return load_npz(c.dataset)
    if c.data_seed is not None:
        return _shared_play(c.episodes, c.episode_steps, c.noise, c.noise_smoothing,
                            c.p_random_action, c.data_seed)
    return play(seed_rng(key), c.episodes, c.episode_steps, c.noise, c.noise_smoothing,
                c.p_random_action, processes=_processes(c.episodes, c.episode_steps), progress=progress)


def evaluate_episodes(acts: Callable, policies, keys: jax.Array, cfg: CubeEvalConfig,
                      goal_rep: str) -> Rollouts:
    """OGBench's evaluation of stacked seeds on the host (module docstring): each seed's key
    gives its episodes' reset seeds (``episodes_per_task`` a task of ``cfg.tasks``) and one act
    key a step; ``acts(policies, keys [S], s [S, B, 28], g [S, B, d_g]) -> [S, B, 5]``.
    Returns :class:`~lazyq_jax.tasks.base.Rollouts` with a leading seed axis: ``agent`` the
    effector and ``obj`` the cube positions ``[S, T + 1, B, 3]`` (metres; the last position
    repeated after an episode ends), ``outcome`` (:data:`CORRECT` or :data:`NOT_PUSHED`),
    ``steps``, ``idle`` (steps whose action was zero), ``ctx``: ``task [S, B]``, ``target [S, B,
    3]`` (the goal's cube position, metres), ``reset_seed [S, B]`` (each episode's
    ``env.reset(seed=...)``: an episode is reproducible with OGBench's env)."""
    n_seeds = int(keys.shape[0])
    task_ids = np.repeat(np.asarray(cfg.tasks), cfg.episodes_per_task)
    b = len(task_ids)
    k_reset, k_run = (jnp.stack(x) for x in zip(*[jax.random.split(k) for k in keys]))
    seeds = np.concatenate([seed_rng(k).integers(0, 2**31 - 1, size=b) for k in k_reset])
    step_keys = jax.vmap(lambda k: jax.random.split(k, cfg.max_steps))(k_run)  # [S, T, 2]
    batch = EpisodeBatch(n_seeds * b, "task", workers=cfg.workers)
    try:
        obs, infos = batch.reset([int(s) for s in seeds], np.tile(task_ids, n_seeds).tolist())
        goal_obs = np.stack([info["goal"] for info in infos])
        g = goal_of(goal_obs, goal_rep).reshape(n_seeds, b, -1)
        done = np.zeros(n_seeds * b, bool)
        steps = np.zeros(n_seeds * b, np.int64)
        idle = np.zeros(n_seeds * b, np.int64)
        effector, cube = [effector_position(obs)], [cube_position(obs)]
        for t in range(cfg.max_steps):
            s = np.asarray(obs, np.float32).reshape(n_seeds, b, OBS_DIM)
            a = np.asarray(acts(policies, step_keys[:, t], s, g), np.float64).reshape(-1, ACTION_DIM)
            live = ~done
            new_obs, success, _ = batch.step(a, live)
            obs = np.where(live[:, None], new_obs, obs)
            steps += live
            idle += live & np.all(a == 0, axis=-1)
            done |= live & success
            effector.append(effector_position(obs))
            cube.append(cube_position(obs))
            if done.all():
                break
    finally:
        batch.close()
    pad = cfg.max_steps + 1 - len(cube)
    effector += [effector[-1]] * pad
    cube += [cube[-1]] * pad
    per_seed = lambda x: np.moveaxis(np.stack(x).reshape(cfg.max_steps + 1, n_seeds, b, 3), 1, 0)
    shape = lambda x: x.reshape(n_seeds, b)
    outcome = np.where(done, CORRECT, NOT_PUSHED).astype(np.int32)
    ctx = {"task": shape(np.tile(task_ids, n_seeds)).astype(np.int32),
           "target": cube_position(goal_obs).reshape(n_seeds, b, 3), "reset_seed": shape(seeds)}
    return Rollouts(per_seed(effector), per_seed(cube), shape(outcome), shape(steps).astype(np.int32),
                    shape(idle).astype(np.int32), None, ctx)


def summarize(rollouts: Rollouts, cfg: CubeEvalConfig) -> dict:
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


class CubeTask(Task):
    """``cube-single-play`` (see the module docstring)."""

    name = "cube-single-play"
    summary = "OGBench's cube-single-play: a UR5e arm places a cube, 28-D observations, box actions"
    collect_config = CubeCollectConfig
    eval_config = CubeEvalConfig
    data_version = 2  # the rows carry their trajectories (Transitions.traj_last)
    rates = (("success_rate", "success (5 tasks)"),
             *((f"task{i}", f"task {i}") for i in range(1, N_TASKS + 1)))

    def __init__(self):
        self.presets = presets()

    def check(self, config: Config) -> None:
        super().check(config)
        check(config)

    def problem(self, config: Config) -> Problem:
        observation_goals = config.collect.goal_rep == "observation"
        return Problem(action_length=1.0, action_set="box", state_scale=1.0,
                       features=self.features(config),
                       goal_features=goal_features if observation_goals else None,
                       state_goal_reward=observation_goals)

    def feature_maps(self, config: Config) -> dict:
        return {"state": None, "cube": cube_features}

    def method_defaults(self, name: str) -> dict:
        """OGBench's cube flags (``impls/hyperparameters.sh``: GCIVL alpha 10, GCIQL 1.0, QRL 0.3,
        CRL 3.0, HIQL alphas 3 with ``subgoal_steps=10``) and its network and batch sizes (3 x 512
        hidden, batch 1024) for every baseline."""
        sizes = {"width": 512, "depth": 4, "batch_size": 1024}
        flags = {"gcivl": {"alpha": 10.0}, "gciql": {"alpha": 1.0}, "qrl": {"alpha": 0.3},
                 "crl": {"alpha": 3.0},
                 "hiql": {"low_alpha": 3.0, "high_alpha": 3.0, "subgoal_steps": 10}}
        return {**sizes, **flags.get(name, {})}

    def collect(self, key, config: Config, *, mesh: Mesh | None = None, progress: bool = True
                ) -> Transitions:
        c = config.collect
        steps = trajectory_transitions(play_data(key, c, progress=progress))
        data, _ = relabel(seed_rng(jax.random.fold_in(key, 1)), steps, c.goals_per_transition,
                          c.p_curgoal, c.p_trajgoal, c.discount)
        if c.goal_rep == "cube":
            data = data.replace(g=np.asarray(goal_features(data.g)), traj_last=None)
        return data.astype_canonical()

    def data_summary(self, data: Transitions, config: Config) -> dict:
        return {"rows": data.size, "successes": int(np.sum(np.asarray(data.done)))}

    def data_table(self, summaries: Sequence[dict]) -> dict:
        return {k: [s[k] for s in summaries] for k in ("rows", "successes")}

    def evaluate(self, act_of, policies, config: Config, seeds: Sequence[int], *,
                 quick: bool = False) -> Evaluation:
        cfg = config.eval
        keys = jnp.stack([purpose_key(int(s) + cfg.seed, "eval") for s in seeds])
        rollouts = evaluate_episodes(seed_acts(act_of), policies, keys, cfg, config.collect.goal_rep)
        per_seed = []
        for i, seed in enumerate(seeds):
            one = jax.tree.map(lambda x, i=i: x[i], rollouts)
            per_seed.append({"seed": int(seed), "eval_seed": int(seed) + cfg.seed,
                             "tasks": summarize(one, cfg)})
        return Evaluation(per_seed, {"tasks": rollouts})

    def seed_rates(self, result: dict) -> dict:
        r = result["tasks"]
        rates = {"success_rate": r["success_rate"], "idle_fraction": r["idle_fraction"]}
        rates.update({f"task{row['task']}": row["success_rate"] for row in r["per_task"]})
        return rates

    def figures(self, out_dir: Path, result: dict, rollouts: dict, config: Config,
                value_fn: Callable | None = None) -> list[Path]:
        out_dir.mkdir(parents=True, exist_ok=True)
        return [plots.rollouts_figure(rollouts["tasks"], result, out_dir / "cube_rollouts.png")]
