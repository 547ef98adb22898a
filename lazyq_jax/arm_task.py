"""The arm task: its data (random joint-space pushes, §V-A-3 in joint space, relabelled
for goals), protocol A in joint space, and the whole run behind ``train --task arm``.

The state is the joint angles ``q`` (``d_s = 3``) with the disk at its start position
(the origin) for every push; the action is a joint move ``dq`` of norm
``ArmConfig.action_length`` (``n_a = 3``); the goal is the push direction angle, the
reward Eq. (15) of the disk's displacement.  As for the finger: ``n_starts`` random
collision-free starts (:func:`lazyq_jax.env.arm.sample_arm_start`), ``moves_per_start``
moves in one random joint direction, ``n_goals`` fresh goals per move, and an episode
ends at a push that moves the disk.
"""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh

from lazyq_jax import plots
from lazyq_jax.checkpoint import save_checkpoint
from lazyq_jax.config import CollectConfig, Config, EvalConfig, to_dict
from lazyq_jax.data import dataset_summary, episodes_to_transitions, repeated_moves, run_episodes
from lazyq_jax.env.arm import ArmConfig, ArmEnv, fingertip_xy, sample_arm_start
from lazyq_jax.evaluate import (Act, Rollouts, _directions, _rollout, direction_outcome, eval_keys,
                                policy_act, summarize_a)
from lazyq_jax.neighbours import find_neighbours
from lazyq_jax.pipeline import RunDirError, _log, run_keys
from lazyq_jax.policy import make_lazy_policy
from lazyq_jax.train import make_train
from lazyq_jax.types import Transitions


def make_arm_episode_fn(env: ArmEnv, config: CollectConfig):
    """``episode(key) -> dict`` of one random joint-space episode, unbatched (vmap it)."""
    arm, pc = env.config, env.config.push

    def episode(key):
        k_start, k_dir, k_goal = jax.random.split(key, 3)
        q0 = sample_arm_start(k_start, arm)
        direction = jax.random.normal(k_dir, (3,), jnp.float32)
        action = arm.action_length * direction / jnp.linalg.norm(direction)
        return repeated_moves(env.step, env.reset(q0), action, k_goal, config, pc,
                              observe=lambda st: st.q)

    return episode


def collect_arm(key: jax.Array, arm: ArmConfig = ArmConfig(),
                config: CollectConfig = CollectConfig(), *, mesh: Mesh | None = None,
                progress: bool = True) -> Transitions:
    """Random joint-space pushes of the arm, relabelled for ``config.n_goals`` goals per move
    (``config.start_range`` and ``config.push`` are not used: the arm's own are).

    Returns ``Transitions`` with ``s, s_next: [N, 3]`` joint angles, ``a: [N, 3]`` the
    chosen joint moves (the env shortens moves that would leave the joint limits), ``g:
    [N]`` goal angles; physics in float64 when ``arm.push.float64``.
    """
    if not isinstance(arm, ArmConfig) or not isinstance(config, CollectConfig):
        raise TypeError("collect_arm needs an ArmConfig and a CollectConfig")
    make = lambda: make_arm_episode_fn(ArmEnv(arm), config)
    eps = run_episodes(key, make, ("arm", arm, config), config.n_starts, config.chunk_size,
                       float64=arm.push.float64, mesh=mesh, progress=progress,
                       desc="collect arm (episodes)")
    return episodes_to_transitions(eps, config.n_goals)


def arm_protocol_a(env: ArmEnv, act: Act, key: jax.Array, cfg: EvalConfig
                   ) -> tuple[Rollouts, jax.Array]:
    """Protocol A (Fig. 4) for the arm: push the disk at the origin toward each of
    ``cfg.n_directions`` goals, ``cfg.episodes_per_direction`` episodes each.

    Starts: :func:`sample_arm_start` conditioned on the fingertip being behind the disk
    (``fingertip . goal_direction < 0``), as the finger's starts in
    :func:`lazyq_jax.evaluate.protocol_a`; ``act(key, q[B, 3], g[B])`` gives joint moves.
    Outcomes as there (:func:`lazyq_jax.evaluate.direction_outcome`).  Returns the
    rollouts (``finger``: the fingertip ``[T + 1, B, 2]``) and the joint angles
    ``[T + 1, B, 3]``.  Summarise with :func:`lazyq_jax.evaluate.summarize_a`.
    """
    arm = env.config
    goals = jnp.repeat(_directions(cfg.n_directions), cfg.episodes_per_direction)
    k_start, k_run = jax.random.split(key)

    def start(k, g):
        behind = lambda q: fingertip_xy(q, arm) @ jnp.stack([jnp.cos(g), jnp.sin(g)]) < 0
        return sample_arm_start(k, arm, extra=behind)

    q0 = jax.vmap(start)(jax.random.split(k_start, goals.shape[0]), goals)
    state = env.reset(q0)
    outcome_of = direction_outcome(arm.push.cos_threshold, arm.push.move_threshold)
    rollouts = _rollout(env, act, k_run, state, lambda st: goals, cfg.max_steps, outcome_of,
                        jnp.zeros(goals.shape, bool), observe=lambda st: st.q,
                        finger_of=lambda st: st.q)
    q = rollouts.finger
    return rollouts._replace(finger=fingertip_xy(q, arm)), q


ARM_RADIUS_S = 0.12  # joint-space neighbourhood radius (rad): one joint move


def arm_state_scale(arm: ArmConfig) -> tuple[float, ...]:
    """Per-joint input scale of the value network: the half-ranges of the joint limits."""
    return tuple((hi - lo) / 2 for lo, hi in zip(arm.joint_lower, arm.joint_upper))


def fit_arm(config: Config, run_dir: str | Path, *, overwrite: bool = False, progress: bool = True,
            radius_s: float = ARM_RADIUS_S, evaluate: bool = True) -> dict:
    """``train --task arm``: the arm's dataset, neighbourhoods, training (a checkpoint per
    cycle), protocol A and figures, for ``config.seed``.

    ``config`` is a run :class:`lazyq_jax.config.Config`: its ``collect`` (starts, moves,
    goals; ``collect.push`` is the disk world), ``neighbours`` (``k``, ``radius_g``,
    ``growth``; the state radius is ``radius_s`` radians in joint space), ``train`` and
    ``eval`` sections are used; the arm is :class:`ArmConfig` with that disk world.
    Writes ``run_dir/{config.json, dataset_summary.json, neighbours.json, metrics.jsonl,
    checkpoints/, eval/results.json, figures/}``; returns the evaluation results.
    Resuming is not supported: an existing run is refused unless ``overwrite``.
    """
    run_dir = Path(run_dir)
    if (run_dir / "checkpoints").exists():
        if not overwrite:
            raise RunDirError(f"{run_dir} already holds an arm run; replace it with --overwrite "
                              "or pick another --run-dir (the arm task cannot --resume)")
        shutil.rmtree(run_dir / "checkpoints")
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "config.json").write_text(json.dumps({"task": "arm", "arm_radius_s": radius_s,
                                                     **to_dict(config)}, indent=1))
    arm = ArmConfig(push=config.collect.push)
    keys = run_keys(config)
    timings = {}

    t = time.perf_counter()
    data = collect_arm(keys["collect"], arm, config.collect, progress=progress)
    timings["dataset_s"] = time.perf_counter() - t
    summary = dataset_summary(data, config.collect.n_goals)
    (run_dir / "dataset_summary.json").write_text(json.dumps(summary, indent=1))
    _log(f"arm dataset: {data.s.shape[0]:,} rows, {summary['moves_that_moved_disk']} of "
         f"{summary['moves']} moves moved the disk ({timings['dataset_s']:.1f} s)")

    nc = config.neighbours
    t = time.perf_counter()
    nb = find_neighbours(keys["neighbours"], data.s, data.g, data.s, data.g, k=nc.k,
                         radius_s=radius_s, radius_g=nc.radius_g, growth=nc.growth)
    timings["neighbours_s"] = time.perf_counter() - t
    level = np.asarray(nb.level)
    levels = {"mean": float(level.mean()), "max": int(level.max()),
              "histogram": np.bincount(level).tolist()}
    (run_dir / "neighbours.json").write_text(json.dumps(levels))
    _log(f"neighbours: level mean {levels['mean']:.2f}, max {levels['max']}, "
         f"{levels['histogram'][0] / level.size:.1%} at level 0 ({timings['neighbours_s']:.1f} s)")

    tc = config.train
    trainer = make_train(tc, arm.action_length, state_dim=3, goal="angle",
                         state_scale=arm_state_scale(arm))
    state = trainer.init(keys["train"])
    run_cycle = jax.jit(trainer.run_cycle)
    metrics_path = run_dir / "metrics.jsonl"
    metrics_path.write_text("")
    t_train = time.perf_counter()
    while int(state.cycle) < tc.cycles:
        t = time.perf_counter()
        state, metrics = run_cycle(state, data, nb.idx)
        record = {"cycle": int(state.cycle), "seconds": round(time.perf_counter() - t, 2),
                  **{k: np.asarray(v).round(5).tolist() for k, v in metrics.items()}}
        save_checkpoint(run_dir / "checkpoints", state, config)
        with metrics_path.open("a") as f:
            f.write(json.dumps(record) + "\n")
        _log(f"cycle {record['cycle']:>2}/{tc.cycles}: loss {record['loss']:.4f}  "
             f"Y {record['target_mean']:+.3f}  clip {record['clip_fraction']:.1%}  "
             f"({record['seconds']:.1f} s)")
    timings["train_s"] = time.perf_counter() - t_train
    value_fn = trainer.value_fn(state)
    results = {"timings": timings}
    if evaluate:
        t = time.perf_counter()
        policy = make_lazy_policy(value_fn, data, gamma=tc.gamma, action_length=arm.action_length,
                                  k=nc.k, radius_s=radius_s, radius_g=nc.radius_g, growth=nc.growth,
                                  max_level=max(config.eval.max_level, levels["max"] + 4))
        rollouts, q = arm_protocol_a(ArmEnv(arm), policy_act(policy), eval_keys(config.eval)[0],
                                     config.eval)
        results["protocol_a"] = summarize_a(rollouts, config.eval)
        timings["protocol_a_s"] = time.perf_counter() - t
        (run_dir / "eval").mkdir(exist_ok=True)
        (run_dir / "eval" / "results.json").write_text(json.dumps(results, indent=1))
        figures = run_dir / "figures"
        figures.mkdir(exist_ok=True)
        plots.fig4_outcomes(results, figures / "fig4_outcomes.png")
        plots.arm_value(value_fn, arm, figures / "arm_value.png")
        plots.arm_trajectories(rollouts, q, arm, config.eval, figures / "arm_trajectories.png")
        a = results["protocol_a"]
        _log(f"protocol A (arm): axis correct {a['axis_correct_rate']:.1%}, all "
             f"{a['overall_correct_rate']:.1%} ({timings['protocol_a_s']:.0f} s) -> {run_dir / 'eval'}")
    (run_dir / "timings.json").write_text(json.dumps({k: round(v, 2) for k, v in timings.items()}))
    return results
