"""The paper's evaluations (§V-B): goal directions (Fig. 4, protocol A) and the long-horizon
task with a high-level controller (Fig. 5, protocol B), as :class:`~lazyq_jax.tasks.base.Protocol`
programs (batched over episodes and seeds); the arm task reuses the outcome tests, the
controller and the summaries (it pushes the same disk)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from lazyq_jax.keys import purpose_key
from lazyq_jax.tasks.base import CORRECT, NOT_PUSHED, WRONG, Protocol, Rollouts, make_protocol
from lazyq_jax.tasks.push.config import EvalConfig
from lazyq_jax.tasks.push.env import PushEnv
from lazyq_jax.tasks.push.reward import disk_moved
from lazyq_jax.tasks.sampling import sample_outside_disk

AXIS_GOALS = np.array([0.0, np.pi / 2, np.pi, -np.pi / 2], np.float32)  # NumPy: importing starts no backend


def directions(n: int) -> jax.Array:
    """``n`` goal directions evenly spaced from 0."""
    return jnp.arange(n, dtype=jnp.float32) * (2 * jnp.pi / n)


def eval_keys(seed: int) -> tuple[jax.Array, jax.Array]:
    """The keys of protocols A and B for evaluation seed ``seed``."""
    k_a, k_b = jax.random.split(purpose_key(seed, "eval"))
    return k_a, k_b


def direction_outcome(cos_min: float, move_threshold: float):
    """Protocol A's outcome of a push: ``(CORRECT or WRONG, ends)``; it ends when the disk
    moved (``|delta| >= move_threshold``), correct when ``cos(delta, g) >= cos_min``."""

    def outcome_of(delta, g, new_state):
        # §V-B counts a push as correct when cos >= 0.9 (Eq. 15's reward demands > 0.9).
        cos = (jnp.sum(delta * jnp.stack([jnp.cos(g), jnp.sin(g)], -1), -1)
               / jnp.maximum(jnp.linalg.norm(delta, axis=-1), 1e-12))
        return jnp.where(cos >= cos_min, CORRECT, WRONG), disk_moved(delta, move_threshold)

    return outcome_of


def protocol_a(env: PushEnv, cfg: EvalConfig) -> Protocol:
    """Fig. 4: push the disk at the origin toward each of ``n_directions`` goals,
    ``episodes_per_direction`` episodes each, at most ``max_steps`` moves.

    The finger starts uniform in ``[-start_range, start_range]^2`` outside the disk with
    ``finger . goal_direction < 0`` (behind the disk).  An episode ends at the first push
    that moves the disk (``|delta| >= move_threshold``): CORRECT if ``cos(delta, g) >= 0.9``
    (§V-B), else WRONG; NOT_PUSHED after ``max_steps``.
    """
    goals = jnp.repeat(directions(cfg.n_directions), cfg.episodes_per_direction)
    contact = env.config.contact_distance

    def start(key):
        def one(k, g):
            behind = lambda x: x @ jnp.stack([jnp.cos(g), jnp.sin(g)]) < 0
            return sample_outside_disk(k, jnp.zeros(2), cfg.start_range, contact, behind)

        finger = jax.vmap(one)(jax.random.split(key, goals.shape[0]), goals)
        return env.reset(finger, jnp.zeros_like(finger)), goals, jnp.zeros(goals.shape, bool)

    outcome = direction_outcome(env.config.cos_threshold, env.config.move_threshold)
    return make_protocol(start, jax.vmap(env.step), lambda st, goals: goals,
                         lambda delta, g, new, ctx: outcome(delta, g, new), lambda st: st.relative,
                         lambda st: (st.finger_xy, st.disk_xy, None), cfg.max_steps)


def protocol_b(env: PushEnv, cfg: EvalConfig) -> Protocol:
    """Fig. 5: reach random targets with axis goals chosen by a high-level controller.

    Disk and target uniform in ``[-long_range, long_range]^2``, the finger uniform outside
    the disk within ``long_finger_box`` of it; the controller and outcomes of
    :func:`long_horizon`.  The rollouts' ``ctx`` holds the targets ``[B, 2]``.
    """
    b, lim, contact = cfg.long_rollouts, cfg.long_range, env.config.contact_distance

    def start(key):
        k_disk, k_target, k_finger = jax.random.split(key, 3)
        disk = jax.random.uniform(k_disk, (b, 2), jnp.float32, -lim, lim)
        target = jax.random.uniform(k_target, (b, 2), jnp.float32, -lim, lim)
        finger = jax.vmap(lambda k, d: sample_outside_disk(k, d, cfg.long_finger_box, contact))(
            jax.random.split(k_finger, b), disk)
        return env.reset(finger, disk), target

    return long_horizon(start, jax.vmap(env.step), cfg, env.config.table_half_size,
                        observe=lambda st: st.relative,
                        record=lambda st: (st.finger_xy, st.disk_xy, None))


def long_horizon(start, step, cfg, table_half_size: float, *, observe, record) -> Protocol:
    """Fig. 5's protocol from ``start(key) -> (state, targets [B, 2])`` (any env state with
    ``disk_xy``): before each step the high-level controller picks the axis goal (0, 90, 180
    or 270 degrees) closest to the direction from the disk to its target; an episode ends
    as a success (CORRECT) when the disk is within ``success_radius`` of its target, as a
    failure (WRONG) when it leaves the table or the physics is not finite, and is
    NOT_PUSHED when ``long_max_steps`` run out.  A disk that starts at its target is a
    success with 0 steps."""

    def controller(st, target) -> jax.Array:
        direction = target - st.disk_xy
        axes = jnp.stack([jnp.cos(AXIS_GOALS), jnp.sin(AXIS_GOALS)], -1)  # [4, 2]
        return jnp.asarray(AXIS_GOALS)[jnp.argmax(direction @ axes.T, axis=-1)]

    def reached(disk, target):
        return jnp.linalg.norm(target - disk, axis=-1) < cfg.success_radius

    def first(key):
        state, target = start(key)
        return state, target, reached(state.disk_xy, target)

    def outcome_of(delta, g, new_state, target):
        ok = reached(new_state.disk_xy, target)
        off = ~jnp.all(jnp.abs(new_state.disk_xy) <= table_half_size, axis=-1)  # NaN is off too
        return jnp.where(ok, CORRECT, WRONG), ok | off

    return make_protocol(first, step, controller, outcome_of, observe, record, cfg.long_max_steps)


def summarize_a(rollouts: Rollouts, n_directions: int, episodes_per_direction: int) -> dict:
    """Protocol A's outcomes per goal direction and the correct rates (axis goals, all)."""
    outcome = np.asarray(rollouts.outcome).reshape(n_directions, episodes_per_direction)
    goals = np.asarray(directions(n_directions))
    per_goal = [{"goal": float(g), "correct": int(np.sum(o == CORRECT)),
                 "wrong": int(np.sum(o == WRONG)), "not_pushed": int(np.sum(o == NOT_PUSHED))}
                for g, o in zip(goals, outcome)]
    final = np.asarray(rollouts.obj)[-1]
    return {"per_goal": per_goal, **direction_rates(per_goal),
            "idle_steps": int(np.sum(np.asarray(rollouts.idle))),
            "non_finite_physics": int(np.sum(~np.all(np.isfinite(final), axis=-1)))}


def direction_rates(per_goal: list[dict]) -> dict:
    """Correct rates over the axis goals (0, 90, 180, 270 degrees), the diagonal goals
    (45 + 90 k degrees) and all goals of protocol A's ``per_goal`` rows (None where no goal
    of the kind was evaluated)."""
    goals = np.array([row["goal"] for row in per_goal])
    correct = np.array([row["correct"] for row in per_goal])
    total = np.array([row["correct"] + row["wrong"] + row["not_pushed"] for row in per_goal])
    phase = np.mod(goals, np.pi / 2)
    axis = np.isclose(phase, 0, atol=1e-5) | np.isclose(phase, np.pi / 2, atol=1e-5)
    diagonal = np.isclose(phase, np.pi / 4, atol=1e-5)
    rate = lambda m: float(correct[m].sum() / total[m].sum()) if m.any() else None  # no such goals
    return {"axis_correct_rate": rate(axis), "diagonal_correct_rate": rate(diagonal),
            "overall_correct_rate": rate(np.ones_like(axis))}


def summarize_b(rollouts: Rollouts) -> dict:
    outcome = np.asarray(rollouts.outcome)
    final = np.asarray(rollouts.obj)[-1]
    return {"successes": int(np.sum(outcome == CORRECT)), "rollouts": int(outcome.size),
            "off_table": int(np.sum(outcome == WRONG)), "out_of_time": int(np.sum(outcome == NOT_PUSHED)),
            "non_finite_physics": int(np.sum(~np.all(np.isfinite(final), axis=-1))),
            "idle_steps": int(np.sum(np.asarray(rollouts.idle)))}


def direction_seed_rates(result: dict) -> dict:
    """A seed's table numbers from protocol A (and B, if it ran): the three correct rates,
    the not-pushed rate, the correct rate per direction, the long-horizon success rate."""
    a = result["protocol_a"]
    correct = np.array([row["correct"] for row in a["per_goal"]])
    total = np.array([row["correct"] + row["wrong"] + row["not_pushed"] for row in a["per_goal"]])
    rates = direction_rates(a["per_goal"])
    rates["not_pushed_rate"] = float(sum(r["not_pushed"] for r in a["per_goal"]) / total.sum())
    rates["per_direction_correct_rate"] = (correct / total).round(6).tolist()
    if "protocol_b" in result:
        b = result["protocol_b"]
        rates.update(long_horizon_successes=b["successes"], long_horizon_rollouts=b["rollouts"],
                     long_horizon_success_rate=b["successes"] / b["rollouts"])
    return rates
