"""The arm task: its data (random joint-space pushes, §V-A-3 in joint space, relabelled
for goals), protocol A and the long-horizon task in joint space, and the whole run
behind ``train --task arm`` / ``--task arm-long``.

Two variants (:class:`ArmTask`, :data:`ARM_TASKS`):

* ``arm``: the state is the joint angles ``q`` (``d_s = 3``) with the disk at its
  start position (the origin) for every push.  Protocol A only: a state without the
  disk cannot say where a moved disk is.
* ``arm-long``: the state is ``(q, disk_scale * disk_xy)`` (``d_s = 5``), the data's
  pushes start with the disk anywhere in ``[-disk_range, disk_range]^2``; protocol A
  (disk at the origin) and the long-horizon task (Fig. 5's high-level controller,
  disk and targets in ``[-long_range, long_range]^2``).

The action is a joint move ``dq`` of norm ``ArmConfig.action_length`` (``n_a = 3``);
the goal is the push direction angle, the reward Eq. (15) of the disk's displacement.
As for the finger: ``n_starts`` random collision-free starts
(:func:`lazyq_jax.env.arm.sample_arm_start`), ``moves_per_start`` moves in one random
joint direction, ``n_goals`` fresh goals per move, and an episode ends at a push that
moves the disk.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh

from lazyq_jax import plots
from lazyq_jax.checkpoint import load_latest_intact, save_checkpoint
from lazyq_jax.config import CollectConfig, Config, ConfigError, EvalConfig, _check, _positive, to_dict
from lazyq_jax.data import (DatasetError, dataset_summary, episodes_to_transitions, load_dataset,
                            repeated_moves, run_episodes, save_dataset)
from lazyq_jax.env.arm import ArmConfig, ArmEnv, ArmState, fingertip_xy, sample_arm_start
from lazyq_jax.evaluate import (Act, Rollouts, _directions, _rollout, direction_outcome, eval_keys,
                                long_horizon_rollout, policy_act, summarize_a, summarize_b)
from lazyq_jax.neighbours import find_neighbours
from lazyq_jax.networks import goal_kind
from lazyq_jax.pipeline import RunDirError, _log, run_keys
from lazyq_jax.policy import make_lazy_policy
from lazyq_jax.train import make_train
from lazyq_jax.types import Transitions


@dataclasses.dataclass(frozen=True)
class ArmTask:
    """What the agent sees of the arm scene, and where the disk starts.

    Attributes:
      disk_range: ``None``: the disk starts at the origin for every push and the state
        is ``q`` (``d_s = 3``).  A number ``r``: the data's pushes start with the disk
        uniform in ``[-r, r]^2`` and the state is ``(q, disk_scale * disk_xy)``
        (``d_s = 5``), which the long-horizon task needs (its disk goes anywhere).
      disk_scale: state units per unit of disk position.  1.2 = 0.12 rad / 0.1: a disk
        offset of one finger move weighs like a joint move of ``action_length`` in the
        neighbourhood distance ``||s - s0|| < radius_s growth^L`` (one radius for all
        state dimensions).
      long_range: the long-horizon task's disk starts and targets, uniform in
        ``[-long_range, long_range]^2`` (at most ``disk_range``: the data must have
        seen the disk there).  The arm reaches behind the disk everywhere in it.  It
        replaces ``EvalConfig.long_range`` (the finger's 0.6: beyond the arm's reach
        behind a disk near the far corners); the rest of ``EvalConfig``'s long-horizon
        settings apply as they are.
    """

    disk_range: float | None = None
    disk_scale: float = 1.2
    long_range: float = 0.3

    def __post_init__(self) -> None:
        _positive(self, "disk_scale", "long_range")
        if self.disk_range is not None:
            _positive(self, "disk_range")
            _check(self.long_range <= self.disk_range,
                   f"ArmTask.long_range={self.long_range} exceeds disk_range={self.disk_range}: "
                   "the data would never have seen the disk there")

    @property
    def disk_in_state(self) -> bool:
        return self.disk_range is not None

    @property
    def state_dim(self) -> int:
        return 5 if self.disk_in_state else 3

    def observe(self, state: ArmState) -> jax.Array:
        """The agent's state ``s [..., state_dim]`` of an :class:`ArmState`."""
        if not self.disk_in_state:
            return state.q
        return jnp.concatenate([state.q, self.disk_scale * state.disk_xy], -1)

    def state_scale(self, arm: ArmConfig) -> tuple[float, ...]:
        """Per-dimension input scale of the value network: the joint limits' half-ranges
        (and the disk coordinates' range in state units)."""
        joints = tuple((hi - lo) / 2 for lo, hi in zip(arm.joint_lower, arm.joint_upper))
        return joints + ((self.disk_scale * self.disk_range,) * 2 if self.disk_in_state else ())


ARM_TASKS = {"arm": ArmTask(), "arm-long": ArmTask(disk_range=0.4)}


def make_arm_episode_fn(env: ArmEnv, config: CollectConfig, task: ArmTask = ArmTask()):
    """``episode(key) -> dict`` of one random joint-space episode, unbatched (vmap it)."""
    arm, pc = env.config, env.config.push

    def episode(key):
        # Three keys with the disk at the origin: the arm task's data as before arm-long.
        k_start, k_dir, k_goal, *k_disk = jax.random.split(key, 4 if task.disk_in_state else 3)
        disk = (jnp.zeros(2, jnp.float32) if not task.disk_in_state else
                jax.random.uniform(k_disk[0], (2,), jnp.float32, -task.disk_range, task.disk_range))
        q0 = sample_arm_start(k_start, arm, disk_xy=disk)
        direction = jax.random.normal(k_dir, (3,), jnp.float32)
        action = arm.action_length * direction / jnp.linalg.norm(direction)
        return repeated_moves(env.step, env.reset(q0, disk), action, k_goal, config, pc,
                              observe=task.observe)

    return episode


def collect_arm(key: jax.Array, arm: ArmConfig = ArmConfig(),
                config: CollectConfig = CollectConfig(), *, task: ArmTask = ArmTask(),
                mesh: Mesh | None = None, progress: bool = True) -> Transitions:
    """Random joint-space pushes of the arm, relabelled for ``config.n_goals`` goals per move
    (``config.start_range`` and ``config.push`` are not used: the arm's own are).

    Returns ``Transitions`` with ``s, s_next: [N, task.state_dim]`` (joint angles, then
    the scaled disk position if ``task.disk_in_state``), ``a: [N, 3]`` the
    chosen joint moves (the env shortens moves that would leave the joint limits), ``g:
    [N]`` goal angles; physics in float64 when ``arm.push.float64``.
    """
    if not (isinstance(arm, ArmConfig) and isinstance(config, CollectConfig)
            and isinstance(task, ArmTask)):
        raise TypeError("collect_arm needs an ArmConfig, a CollectConfig and an ArmTask")
    make = lambda: make_arm_episode_fn(ArmEnv(arm), config, task)
    eps = run_episodes(key, make, ("arm", arm, config, task), config.n_starts, config.chunk_size,
                       float64=arm.push.float64, mesh=mesh, progress=progress,
                       desc="collect arm (episodes)")
    return episodes_to_transitions(eps, config.n_goals)


def arm_protocol_a(env: ArmEnv, act: Act, key: jax.Array, cfg: EvalConfig,
                   task: ArmTask = ArmTask()) -> tuple[Rollouts, jax.Array]:
    """Protocol A (Fig. 4) for the arm: push the disk at the origin toward each of
    ``cfg.n_directions`` goals, ``cfg.episodes_per_direction`` episodes each.

    Starts: :func:`sample_arm_start` conditioned on the fingertip being behind the disk
    (``fingertip . goal_direction < 0``), as the finger's starts in
    :func:`lazyq_jax.evaluate.protocol_a`; ``act(key, s[B, task.state_dim], g[B])`` gives
    joint moves.
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
                        jnp.zeros(goals.shape, bool), observe=task.observe,
                        finger_of=lambda st: st.q)
    q = rollouts.finger
    return rollouts._replace(finger=fingertip_xy(q, arm)), q


def arm_protocol_b(env: ArmEnv, act: Act, key: jax.Array, cfg: EvalConfig, task: ArmTask
                   ) -> tuple[Rollouts, jax.Array, jax.Array]:
    """The long-horizon task (Fig. 5) for the arm: ``cfg.long_rollouts`` rollouts of at
    most ``cfg.long_max_steps`` joint moves; disk and target uniform in
    ``[-task.long_range, task.long_range]^2``, the arm's start
    (:func:`sample_arm_start`) with the fingertip outside the disk within
    ``cfg.long_finger_box`` of it; the high-level controller and outcomes of
    :func:`lazyq_jax.evaluate.long_horizon_rollout` (off the table: the push world's
    table).  Needs ``task.disk_in_state``.  Returns the rollouts (``finger``: the
    fingertip), the targets ``[B, 2]`` and the joint angles ``[T + 1, B, 3]``;
    summarise with :func:`lazyq_jax.evaluate.summarize_b`.
    """
    if not task.disk_in_state:
        raise ConfigError("the arm's long-horizon task needs the disk in the state "
                          "(ArmTask(disk_range=...), `--task arm-long`)")
    arm = env.config
    b, lim = cfg.long_rollouts, task.long_range
    k_disk, k_target, k_start, k_run = jax.random.split(key, 4)
    disk = jax.random.uniform(k_disk, (b, 2), jnp.float32, -lim, lim)
    target = jax.random.uniform(k_target, (b, 2), jnp.float32, -lim, lim)
    near = dataclasses.replace(arm, start_range=cfg.long_finger_box)
    q0 = jax.vmap(lambda k, d: sample_arm_start(k, near, disk_xy=d))(jax.random.split(k_start, b), disk)
    rollouts = long_horizon_rollout(env, act, k_run, env.reset(q0, disk), target, cfg,
                                    arm.push.table_half_size, observe=task.observe,
                                    finger_of=lambda st: st.q)
    q = rollouts.finger
    return rollouts._replace(finger=fingertip_xy(q, arm)), target, q


ARM_RADIUS_S = 0.12  # joint-space neighbourhood radius (rad): one joint move

# Config fields that only the finger's push task reads, with what the arm uses instead.
ARM_UNUSED_FIELDS = {
    "collect.start_range": "the arm starts from random joint angles (ArmConfig)",
    "eval.start": "protocol A starts the arm from random joint angles",
    "eval.start_range": "protocol A starts the arm from random joint angles",
    "eval.long_range": "the long-horizon range is ArmTask.long_range (0.3 for arm-long)",
    "online": "the arm learns offline only",
    "parallel": "the arm runs in one process on one device",
}


def check_arm_overrides(assignments: list[str]) -> None:
    """Refuse ``--set`` overrides that the arm task would silently ignore."""
    for assignment in assignments:
        dotted = assignment.split("=", 1)[0].strip()
        for field, instead in ARM_UNUSED_FIELDS.items():
            if dotted == field or dotted.startswith(field + "."):
                raise ConfigError(f"--set {dotted} has no effect on the arm task: {instead}; "
                                  "drop it (or train --task push)")


def fit_arm(config: Config, run_dir: str | Path, *, task: ArmTask = ArmTask(), resume: bool = False,
            overwrite: bool = False, progress: bool = True, radius_s: float = ARM_RADIUS_S,
            evaluate: bool = True) -> dict:
    """``train --task arm|arm-long``: the arm's dataset, neighbourhoods, training (a
    checkpoint per cycle), protocol A (and the long-horizon task when the disk is in the
    state) and figures, for ``config.seed``.

    ``config`` is a run :class:`lazyq_jax.config.Config`: its ``collect`` (starts, moves,
    goals; ``collect.push`` is the disk world), ``neighbours`` (``k``, ``radius_g``,
    ``growth``; the state radius is ``radius_s`` in state units: radians in joint space),
    ``train`` and ``eval`` sections are used; the arm is :class:`ArmConfig` with that
    disk world.  Writes ``run_dir/{config.json, dataset.npz, dataset_summary.json,
    neighbours.json, metrics.jsonl, checkpoints/, eval/results.json, figures/}``; returns
    the evaluation results.

    An existing run is refused unless ``resume`` (continue from its newest intact
    checkpoint: same task, radius, seed, data and neighbour settings, compatible
    training settings; ``train.cycles`` may grow) or ``overwrite`` (start afresh; it wins
    over ``resume``, as for :func:`lazyq_jax.pipeline.fit`).
    The neighbourhoods are recomputed from the saved dataset and the run's key.
    """
    run_dir = Path(run_dir)
    if not isinstance(task, ArmTask):
        raise TypeError(f"fit_arm needs an ArmTask, got {type(task).__name__}")
    resume = resume and not overwrite  # overwrite wins: `make train` always passes --resume
    meta = {"task": "arm", "arm_task": dataclasses.asdict(task), "arm_radius_s": radius_s,
            **to_dict(config)}
    ckpt_dir, meta_path = run_dir / "checkpoints", run_dir / "config.json"
    stored = json.loads(meta_path.read_text()) if meta_path.exists() else {}
    differ = [k for k in ("task", "arm_task", "arm_radius_s", "seed", "collect", "neighbours")
              if stored.get(k) != meta[k]]
    if ckpt_dir.exists() and overwrite:
        shutil.rmtree(ckpt_dir)
    elif ckpt_dir.exists() and not resume:
        raise RunDirError(f"{run_dir} already holds an arm run; continue it with --resume, "
                          "replace it with --overwrite or pick another --run-dir")
    elif ckpt_dir.exists():
        if differ:
            raise RunDirError(f"{run_dir} holds an arm run with other {', '.join(differ)}; "
                              "resume it with its own settings, or use --overwrite")
    # The saved dataset is this run's if the stored task, seed and collect settings are.
    same_data = not {"task", "arm_task", "seed", "collect"} & set(differ)
    run_dir.mkdir(parents=True, exist_ok=True)
    meta_path.write_text(json.dumps(meta, indent=1))
    arm = ArmConfig(push=config.collect.push)
    keys = run_keys(config)
    timings = {}

    t = time.perf_counter()
    data = _arm_dataset(config, arm, task, run_dir, keys["collect"], progress, reuse=same_data)
    timings["dataset_s"] = time.perf_counter() - t

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
    trainer = make_train(tc, arm.action_length, state_dim=data.s.shape[1], goal=goal_kind(data.g),
                         state_scale=task.state_scale(arm))
    state = None
    if resume and ckpt_dir.exists():
        found = load_latest_intact(ckpt_dir, config, target=jax.eval_shape(trainer.init, keys["train"]),
                                   warn=_log)
        if found is not None:
            state = found[0]
            _log(f"resuming after cycle {int(state.cycle)} from {ckpt_dir}")
    metrics_path = run_dir / "metrics.jsonl"
    if state is None:
        state = trainer.init(keys["train"])
        metrics_path.write_text("")
    run_cycle = jax.jit(trainer.run_cycle)
    t_train = time.perf_counter()
    while int(state.cycle) < tc.cycles:
        t = time.perf_counter()
        state, metrics = run_cycle(state, data, nb.idx)
        record = {"cycle": int(state.cycle), "seconds": round(time.perf_counter() - t, 2),
                  **{k: np.asarray(v).round(5).tolist() for k, v in metrics.items()}}
        save_checkpoint(ckpt_dir, state, config)
        with metrics_path.open("a") as f:
            f.write(json.dumps(record) + "\n")
        _log(f"cycle {record['cycle']:>2}/{tc.cycles}: loss {record['loss']:.4f}  "
             f"Y {record['target_mean']:+.3f}  clip {record['clip_fraction']:.1%}  "
             f"({record['seconds']:.1f} s)")
    timings["train_s"] = time.perf_counter() - t_train
    results = {"timings": timings}
    if evaluate:
        value_fn = trainer.value_fn(state)
        policy = make_lazy_policy(value_fn, data, gamma=tc.gamma, action_length=arm.action_length,
                                  k=nc.k, radius_s=radius_s, radius_g=nc.radius_g, growth=nc.growth,
                                  max_level=max(config.eval.max_level, levels["max"] + 4))
        results = evaluate_arm(ArmEnv(arm), policy_act(policy), config.eval, task, value_fn,
                               run_dir, config, timings)
    (run_dir / "timings.json").write_text(json.dumps({k: round(v, 2) for k, v in timings.items()}))
    return results


def _arm_dataset(config: Config, arm: ArmConfig, task: ArmTask, run_dir: Path, key: jax.Array,
                 progress: bool, reuse: bool) -> Transitions:
    """``run_dir/dataset.npz`` if ``reuse`` (the run directory's stored task matches) and
    the file holds this run's data (collect settings, seed), else collected and saved there."""
    path = run_dir / "dataset.npz"
    if reuse and path.exists():
        try:
            data, stored, seed = load_dataset(path)
            if stored == config.collect and seed == config.seed:
                _log(f"arm dataset: reusing {path} ({data.size:,} rows)")
                return data
        except DatasetError as e:
            _log(f"arm dataset: ignoring unusable {path} ({e}); collecting anew")
    t = time.perf_counter()
    data = collect_arm(key, arm, config.collect, task=task, progress=progress)
    summary = dataset_summary(data, config.collect.n_goals)
    save_dataset(path, data, config.collect, seed=config.seed)
    (run_dir / "dataset_summary.json").write_text(json.dumps(summary, indent=1))
    _log(f"arm dataset: {data.size:,} rows, {summary['moves_that_moved_disk']} of "
         f"{summary['moves']} moves moved the disk ({time.perf_counter() - t:.1f} s)")
    return data


def evaluate_arm(env: ArmEnv, act: Act, cfg: EvalConfig, task: ArmTask, value_fn, run_dir: Path,
                 config: Config, timings: dict | None = None) -> dict:
    """Protocol A, and the long-horizon task if ``task.disk_in_state``, with figures;
    writes ``run_dir/eval/results.json`` (with ``timings``, to which the evaluation's are
    added) and ``run_dir/figures/``; returns the results."""
    timings = {} if timings is None else timings
    arm, results = env.config, {"timings": timings}
    key_a, key_b = eval_keys(cfg)
    t = time.perf_counter()
    rollouts, q = arm_protocol_a(env, act, key_a, cfg, task)
    results["protocol_a"] = summarize_a(rollouts, cfg)
    timings["protocol_a_s"] = time.perf_counter() - t
    a = results["protocol_a"]
    _log(f"protocol A (arm): axis correct {a['axis_correct_rate']:.1%}, all "
         f"{a['overall_correct_rate']:.1%} ({timings['protocol_a_s']:.0f} s)")
    figures = run_dir / "figures"
    figures.mkdir(exist_ok=True)
    if task.disk_in_state:
        t = time.perf_counter()
        rollouts_b, targets, q_b = arm_protocol_b(env, act, key_b, cfg, task)
        results["protocol_b"] = summarize_b(rollouts_b)
        timings["protocol_b_s"] = time.perf_counter() - t
        b = results["protocol_b"]
        _log(f"long horizon (arm): {b['successes']}/{b['rollouts']} reached their targets "
             f"({timings['protocol_b_s']:.0f} s)")
        plots.fig5_trajectories(rollouts_b, targets, results, config, cfg.success_radius,
                                figures / "fig5_long_horizon.png")
    (run_dir / "eval").mkdir(exist_ok=True)
    (run_dir / "eval" / "results.json").write_text(json.dumps(results, indent=1))
    plots.fig4_outcomes(results, figures / "fig4_outcomes.png")
    disk_at_origin = lambda q: task.observe(ArmState(q, jnp.zeros(q.shape[:-1] + (2,), q.dtype)))
    plots.arm_value(value_fn, arm, figures / "arm_value.png", state_of=disk_at_origin)
    plots.arm_trajectories(rollouts, q, arm, cfg, figures / "arm_trajectories.png")
    return results
