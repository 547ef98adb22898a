"""The paper's evaluations (§V-B) of a trained run: goal directions (Fig. 4) and the
long-horizon task with a high-level controller (Fig. 5).  Rollouts are batched over
episodes and run inside ``lax.scan`` with done masks."""

from __future__ import annotations

import dataclasses
import functools
import json
import time
from pathlib import Path
from typing import Callable, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from lazyq_jax.checkpoint import CheckpointError, load_checkpoint
from lazyq_jax.config import EvalConfig, PushConfig, to_dict
from lazyq_jax.data import DatasetError, load_dataset
from lazyq_jax.env import PushEnv, disk_moved, sample_outside_disk
from lazyq_jax.policy import LazyPolicy, lazy_policy, make_lazy_policy
from lazyq_jax.parallel import over_seeds
from lazyq_jax.pipeline import purpose_key, state_bounds
from lazyq_jax.train import make_train_for

NOT_PUSHED, CORRECT, WRONG = 0, 1, 2
AXIS_GOALS = np.array([0.0, np.pi / 2, np.pi, -np.pi / 2], np.float32)  # NumPy: importing starts no backend


class Rollouts(NamedTuple):
    finger: jax.Array  # [T + 1, B, 2]
    disk: jax.Array  # [T + 1, B, 2]
    outcome: jax.Array  # [B] int
    steps: jax.Array  # [B] steps taken
    lost: jax.Array  # [B] steps at which the policy found no neighbourhood


def _directions(n: int) -> jax.Array:
    return jnp.arange(n, dtype=jnp.float32) * (2 * jnp.pi / n)


Act = Callable[[jax.Array, jax.Array, jax.Array], tuple[jax.Array, jax.Array]]


def policy_act(policy: LazyPolicy) -> Act:
    """``act(key, s[B, 2], g[B]) -> (actions[B, 2], found[B])`` of the lazy policy (Eq. 9)."""

    def act(key, s, g):
        action, _, found = lazy_policy(policy, key, s, g)
        return action, found

    return act


def protocol_a(env: PushEnv, act: Act, key: jax.Array, cfg: EvalConfig) -> Rollouts:
    """Fig. 4: push the disk at the origin toward each of ``n_directions`` goals.

    The finger starts uniform in ``[-start_range, start_range]^2`` outside the disk with
    ``finger . goal_direction < 0`` (behind the disk).  An episode ends at the first push
    that moves the disk (``|delta| >= move_threshold``): CORRECT if ``cos(delta, g) >= 0.9``
    (§V-B), else WRONG; NOT_PUSHED after ``max_steps``.
    """
    goals = jnp.repeat(_directions(cfg.n_directions), cfg.episodes_per_direction)
    k_start, k_run = jax.random.split(key)
    contact = env.config.contact_distance

    def start(k, g):
        behind = lambda x: x @ jnp.stack([jnp.cos(g), jnp.sin(g)]) < 0
        return sample_outside_disk(k, jnp.zeros(2), cfg.start_range, contact, behind)

    finger = jax.vmap(start)(jax.random.split(k_start, goals.shape[0]), goals)
    state = env.reset(finger, jnp.zeros_like(finger))
    cos_min = env.config.cos_threshold

    outcome_of = direction_outcome(cos_min, env.config.move_threshold)
    done0 = jnp.zeros(goals.shape, bool)
    return _rollout(env, act, k_run, state, lambda st: goals, cfg.max_steps, outcome_of, done0)


def direction_outcome(cos_min: float, move_threshold: float):
    """Protocol A's outcome of a push: ``(CORRECT or WRONG, ends)``; it ends when the disk
    moved (``|delta| >= move_threshold``), correct when ``cos(delta, g) >= cos_min``."""

    def outcome_of(delta, g, new_state):
        # §V-B counts a push as correct when cos >= 0.9 (Eq. 15's reward demands > 0.9).
        cos = (jnp.sum(delta * jnp.stack([jnp.cos(g), jnp.sin(g)], -1), -1)
               / jnp.maximum(jnp.linalg.norm(delta, axis=-1), 1e-12))
        return jnp.where(cos >= cos_min, CORRECT, WRONG), disk_moved(delta, move_threshold)

    return outcome_of


def protocol_b(env: PushEnv, act: Act, key: jax.Array, cfg: EvalConfig,
               table_half_size: float) -> tuple[Rollouts, jax.Array]:
    """Fig. 5: reach random targets with axis goals chosen by a high-level controller.

    Returns the rollouts (outcome CORRECT = success, WRONG = off the table or
    non-finite physics, NOT_PUSHED = out of time) and the targets ``[B, 2]``.  A
    rollout whose disk starts within ``success_radius`` of its target is a success
    with 0 steps.
    """
    b = cfg.long_rollouts
    k_disk, k_target, k_finger, k_run = jax.random.split(key, 4)
    lim = cfg.long_range
    disk = jax.random.uniform(k_disk, (b, 2), jnp.float32, -lim, lim)
    target = jax.random.uniform(k_target, (b, 2), jnp.float32, -lim, lim)
    contact = env.config.contact_distance
    finger = jax.vmap(lambda k, d: sample_outside_disk(k, d, cfg.long_finger_box, contact))(
        jax.random.split(k_finger, b), disk)
    state = env.reset(finger, disk)
    return long_horizon_rollout(env, act, k_run, state, target, cfg, table_half_size), target


def long_horizon_rollout(env, act, key: jax.Array, state, target: jax.Array, cfg: EvalConfig,
                         table_half_size: float, **observe) -> Rollouts:
    """Fig. 5's rollouts from ``state`` (any env whose state has ``disk_xy``): before each
    step the high-level controller picks the axis goal (0, 90, 180 or 270 degrees)
    closest to the direction from the disk to ``target [B, 2]``; an episode ends as a
    success (CORRECT) when the disk is within ``success_radius`` of its target, as a
    failure (WRONG) when it leaves the table or the physics is not finite, and is
    NOT_PUSHED when ``long_max_steps`` run out.  ``observe``: :func:`_rollout`'s
    ``observe`` / ``finger_of`` for other tasks than the finger."""

    def controller(st) -> jax.Array:
        direction = target - st.disk_xy
        axes = jnp.stack([jnp.cos(AXIS_GOALS), jnp.sin(AXIS_GOALS)], -1)  # [4, 2]
        return jnp.asarray(AXIS_GOALS)[jnp.argmax(direction @ axes.T, axis=-1)]

    def reached(disk):
        return jnp.linalg.norm(target - disk, axis=-1) < cfg.success_radius

    def outcome_of(delta, g, new_state):
        ok = reached(new_state.disk_xy)
        off = ~jnp.all(jnp.abs(new_state.disk_xy) <= table_half_size, axis=-1)  # NaN is off too
        return jnp.where(ok, CORRECT, WRONG), ok | off

    return _rollout(env, act, key, state, controller, cfg.long_max_steps, outcome_of,
                    reached(state.disk_xy), **observe)


def _rollout(env, act, key, state, goal_of, steps, outcome_of, done0, *,
             observe=lambda st: st.relative, finger_of=lambda st: st.finger_xy) -> Rollouts:
    """Batched episodes in one ``lax.scan``; finished episodes stay frozen.

    ``done0[B]``: episodes that are already CORRECT before the first step.
    ``observe(state)``: the agent's state ``s`` (the push task: the finger relative
    to the disk); ``finger_of(state)``: the finger (or fingertip) on the table.
    """
    batch = done0.shape[0]
    step = jax.vmap(env.step)

    def body(carry, k):
        state, done, outcome, n_steps, lost = carry
        g = goal_of(state)
        action, found = act(k, observe(state), g)
        new_state, delta = step(state, action)
        new_outcome, ends = outcome_of(delta, g, new_state)
        live = ~done
        state = jax.tree.map(lambda new, old: jnp.where(live[:, None], new, old), new_state, state)
        outcome = jnp.where(live & ends, new_outcome, outcome)
        carry = (state, done | ends, outcome, n_steps + live, lost + (live & ~found))
        return carry, (finger_of(state), state.disk_xy)

    zeros = jnp.zeros(batch, jnp.int32)
    init = (state, done0, jnp.where(done0, CORRECT, NOT_PUSHED), zeros, zeros)
    (_, _, outcome, n_steps, lost), (fingers, disks) = jax.lax.scan(
        body, init, jax.random.split(key, steps))
    fingers = jnp.concatenate([finger_of(state)[None], fingers])
    disks = jnp.concatenate([state.disk_xy[None], disks])
    return Rollouts(fingers, disks, outcome, n_steps, lost)


def summarize_a(rollouts: Rollouts, cfg: EvalConfig) -> dict:
    outcome = np.asarray(rollouts.outcome).reshape(cfg.n_directions, cfg.episodes_per_direction)
    goals = np.asarray(_directions(cfg.n_directions))
    per_goal = [{"goal": float(g), "correct": int(np.sum(o == CORRECT)),
                 "wrong": int(np.sum(o == WRONG)), "not_pushed": int(np.sum(o == NOT_PUSHED))}
                for g, o in zip(goals, outcome)]
    axis = np.isclose(np.mod(goals, np.pi / 2), 0, atol=1e-5) | np.isclose(
        np.mod(goals, np.pi / 2), np.pi / 2, atol=1e-5)
    rate = lambda rows: float(np.mean(rows == CORRECT)) if rows.size else float("nan")
    final = np.asarray(rollouts.disk)[-1]
    return {"per_goal": per_goal, "axis_correct_rate": rate(outcome[axis]),
            "overall_correct_rate": rate(outcome), "policy_steps_without_neighbours":
            int(np.sum(np.asarray(rollouts.lost))),
            "non_finite_physics": int(np.sum(~np.all(np.isfinite(final), axis=-1)))}


def direction_rates(summary_a: dict) -> dict:
    """Protocol A's correct rates (of :func:`summarize_a`) over the axis goals (0, 90,
    180, 270 degrees), the diagonal goals (45 + 90 k degrees) and all goals."""
    goals = np.array([row["goal"] for row in summary_a["per_goal"]])
    correct = np.array([row["correct"] for row in summary_a["per_goal"]])
    total = np.array([row["correct"] + row["wrong"] + row["not_pushed"]
                      for row in summary_a["per_goal"]])
    diagonal = np.isclose(np.mod(goals, np.pi / 2), np.pi / 4, atol=1e-5)
    rate = lambda m: float(correct[m].sum() / total[m].sum()) if m.any() else float("nan")
    return {"axis_correct_rate": summary_a["axis_correct_rate"],
            "diagonal_correct_rate": rate(diagonal),
            "overall_correct_rate": summary_a["overall_correct_rate"]}


def summarize_b(rollouts: Rollouts) -> dict:
    outcome = np.asarray(rollouts.outcome)
    final = np.asarray(rollouts.disk)[-1]
    return {"successes": int(np.sum(outcome == CORRECT)), "rollouts": int(outcome.size),
            "off_table": int(np.sum(outcome == WRONG)), "out_of_time": int(np.sum(outcome == NOT_PUSHED)),
            "non_finite_physics": int(np.sum(~np.all(np.isfinite(final), axis=-1))),
            "policy_steps_without_neighbours": int(np.sum(np.asarray(rollouts.lost)))}


class EvalError(ValueError):
    """The run directory cannot be evaluated (no checkpoint, no dataset, mismatch)."""


def load_run(run_dir: Path):
    """``(config, state, trainer, data)`` of a finished run; nothing is retrained."""
    run_dir = Path(run_dir)
    try:
        state, config = load_checkpoint(run_dir / "checkpoints")
    except CheckpointError as e:
        raise EvalError(f"{run_dir}: cannot evaluate: {e}") from e
    data, collect_cfg, seed = load_dataset(run_dir / "dataset.npz")
    if collect_cfg != config.collect or seed != config.seed:
        raise EvalError(f"{run_dir}/dataset.npz was not collected with the checkpoint's config and "
                        "seed; re-run `python -m lazyq_jax train` for this run directory")
    return config, state, make_train_for(config), data


def run_policy(config, value_fn, data, max_level: int) -> LazyPolicy:
    """The lazy policy of a run: its dataset, neighbourhood settings, gamma and trained V
    (its grid over :func:`lazyq_jax.pipeline.state_bounds`, as in training)."""
    nc = config.neighbours
    return make_lazy_policy(value_fn, data, gamma=config.train.gamma,
                            action_length=config.collect.push.action_length, k=nc.k,
                            radius_s=nc.radius_s, radius_g=nc.radius_g, growth=nc.growth,
                            max_level=max_level, bounds=state_bounds(config, data.s))


def eval_keys(cfg: EvalConfig) -> tuple[jax.Array, jax.Array]:
    """The keys of protocols A and B for ``cfg.seed``."""
    k_a, k_b = jax.random.split(purpose_key(cfg.seed, "eval"))
    return k_a, k_b


def evaluate_stacked(push: PushConfig, cfg: EvalConfig, act_of: Callable, policies,
                     seeds: Sequence[int]) -> tuple[list[dict], Rollouts, jax.Array]:
    """Both protocols for several trained agents at once (one per seed), in one program.

    ``policies``: a pytree whose leaves are stacked on a leading seed axis;
    ``act_of(policy)`` turns one seed's slice into an :data:`Act`.  Seed ``i`` is
    evaluated with ``eval.seed = seeds[i]``: the same episodes as
    :func:`evaluate_run` of a run with that evaluation seed.  Protocols A and B are
    ``vmap``-ed over the seeds.  Returns ``(results per seed, protocol-B rollouts,
    protocol-B targets)`` (rollouts and targets stacked over seeds).
    """
    env = PushEnv(push)  # float32 physics, as evaluate_run
    keys = [eval_keys(dataclasses.replace(cfg, seed=int(s))) for s in seeds]
    k_a, k_b = (jnp.stack([k[i] for k in keys]) for i in (0, 1))
    run_a = over_seeds(lambda p, k: protocol_a(env, act_of(p), k, cfg), len(seeds))
    run_b = over_seeds(lambda p, k: protocol_b(env, act_of(p), k, cfg, push.table_half_size),
                       len(seeds))
    rollouts_a = jax.device_get(run_a(policies, k_a))
    rollouts_b, targets = jax.device_get(run_b(policies, k_b))
    per_seed = []
    for i, seed in enumerate(seeds):
        pick = lambda tree: jax.tree.map(lambda x: x[i], tree)
        per_seed.append({"protocol_a": summarize_a(pick(rollouts_a), cfg),
                         "protocol_b": summarize_b(pick(rollouts_b)), "seed": int(seed),
                         "eval_config": to_dict(dataclasses.replace(cfg, seed=int(seed)))})
    return per_seed, rollouts_b, targets


@functools.lru_cache(maxsize=8)
def _protocol_programs(push: PushConfig, cfg: EvalConfig):
    """Jitted ``(run_a, run_b)(policy, key)`` per world and evaluation config, kept so
    that evaluating again in one process (another checkpoint, the same shapes) does not
    compile again."""
    env = PushEnv(push)  # float32 physics here (see the README's design notes)
    run_a = jax.jit(lambda p, k: protocol_a(env, policy_act(p), k, cfg))
    run_b = jax.jit(lambda p, k: protocol_b(env, policy_act(p), k, cfg, push.table_half_size))
    return run_a, run_b


def evaluate_run(run_dir: str | Path, eval_config: EvalConfig | None = None, *,
                 figures: bool = True) -> dict:
    """Reload a run's checkpoint and dataset, run protocols A and B, write
    ``run_dir/eval/results.json`` (and figures into ``run_dir/figures``)."""
    run_dir = Path(run_dir)
    try:
        state, config = load_checkpoint(run_dir / "checkpoints")
    except CheckpointError as e:
        raise EvalError(f"{run_dir}: cannot evaluate: {e}") from e
    if config.online.rounds:  # an online run: its policy acts on the data it gathered
        from lazyq_jax.online import evaluate_online_run

        config = dataclasses.replace(config, eval=eval_config or config.eval)
        try:
            return evaluate_online_run(run_dir, state, config, figures=figures)
        except DatasetError as e:
            raise EvalError(f"{run_dir}: cannot evaluate: {e}") from e
    config, state, trainer, data = load_run(run_dir)
    cfg = eval_config or config.eval
    t = time.perf_counter()
    policy = run_policy(config, trainer.value_fn(state), data, cfg.max_level)
    k_a, k_b = eval_keys(cfg)
    run_a, run_b = _protocol_programs(config.collect.push, cfg)
    rollouts_a = jax.device_get(run_a(policy, k_a))
    rollouts_b, targets = jax.device_get(run_b(policy, k_b))
    results = {"protocol_a": summarize_a(rollouts_a, cfg), "protocol_b": summarize_b(rollouts_b),
               "seed": cfg.seed, "eval_config": to_dict(cfg), "checkpoint": str(run_dir / "checkpoints" / str(int(state.cycle))),
               "seconds": round(time.perf_counter() - t, 1)}
    out = run_dir / "eval"
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps(results, indent=1))
    if figures:
        from lazyq_jax import plots

        plots.write_all(run_dir / "figures", trainer.value_fn(state), results, rollouts_b, targets,
                        config, cfg)
    return results
