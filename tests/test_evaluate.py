"""The lazy policy and the push task's evaluation protocols; re-evaluating a trained run."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import cli

from lazyq_jax.run import RunDirError, evaluate_run
from lazyq_jax.tasks.base import CORRECT, NOT_PUSHED, WRONG, run_protocol, seed_acts
from lazyq_jax.tasks.push import EvalConfig
from lazyq_jax.tasks.push.protocols import protocol_a, protocol_b, summarize_a, summarize_b


def test_evaluation_refuses_a_directory_without_a_run(tmp_path):
    with pytest.raises(RunDirError, match="no run here"):
        evaluate_run(tmp_path)
    out = cli("evaluate", "--run-dir", str(tmp_path), seconds=120)
    assert out.returncode == 2 and "no run here" in out.stderr and "Traceback" not in out.stderr


def fixed(fn):
    """A stand-in method with a fixed rule ``fn(s, g)``: ``act_of(policy) -> act``."""
    return lambda policy: (lambda key, s, g: fn(s, g))


def run_one(program, act_of, key):
    """One seed's episodes of ``program`` (a Protocol) under the fixed rule."""
    rollouts = run_protocol(program, seed_acts(act_of), jnp.zeros(1), key[None])
    return jax.tree.map(lambda x: x[0], rollouts)


A_CFG = EvalConfig(n_directions=8, episodes_per_direction=4, max_steps=12, start_range=0.6)
TOWARD_DISK, STILL = fixed(lambda s, g: -s), fixed(lambda s, g: jnp.zeros_like(s))


def test_protocol_a_starts_behind_and_classifies_pushes(env):
    r = run_one(protocol_a(env, A_CFG), TOWARD_DISK, jax.random.PRNGKey(0))
    goals = np.repeat(np.arange(8) * np.pi / 4, 4)
    direction = np.stack([np.cos(goals), np.sin(goals)], 1)
    start = r.agent[0]
    assert np.all(np.sum(start * direction, 1) < 0)  # behind the disk w.r.t. the goal
    assert np.all(np.linalg.norm(start, axis=1) > 0.31) and np.all(np.abs(start) <= 0.6)
    assert np.all(r.outcome != NOT_PUSHED)  # heading for the centre always hits the disk
    # Independent classification from the recorded trajectory: the disk only moves
    # in the episode's last (frozen) step, by the push that ended it.
    delta = r.obj[-1] - r.obj[0]
    cos = np.sum(delta * direction, 1) / np.linalg.norm(delta, axis=1)
    np.testing.assert_array_equal(r.outcome, np.where(cos >= 0.9, CORRECT, WRONG))
    assert {CORRECT, WRONG} <= set(r.outcome.tolist())  # both classes occur
    summary = summarize_a(r, A_CFG.n_directions, A_CFG.episodes_per_direction)
    assert sum(row["correct"] for row in summary["per_goal"]) == int(np.sum(r.outcome == CORRECT))
    assert summary["idle_steps"] == 0


def test_a_policy_that_does_not_move_never_pushes_and_is_idle(env):
    r = run_one(protocol_a(env, A_CFG), STILL, jax.random.PRNGKey(1))
    assert np.all(r.outcome == NOT_PUSHED) and np.all(r.steps == A_CFG.max_steps)
    assert np.all(r.idle == A_CFG.max_steps)  # every step a zero action
    assert r.agent.shape == (A_CFG.max_steps + 1, 32, 2)


def test_protocol_b_success_at_start_and_out_of_time(env):
    everywhere = EvalConfig(long_rollouts=6, long_max_steps=5, success_radius=5.0)
    r = run_one(protocol_b(env, everywhere), STILL, jax.random.PRNGKey(2))
    assert np.all(r.outcome == CORRECT) and np.all(r.steps == 0)
    tight = EvalConfig(long_rollouts=6, long_max_steps=5, success_radius=1e-4)
    r = run_one(protocol_b(env, tight), STILL, jax.random.PRNGKey(2))
    assert np.all(r.outcome == NOT_PUSHED) and np.all(r.steps == 5) and r.ctx.shape == (6, 2)
    summary = summarize_b(r)
    assert summary["out_of_time"] == 6 and summary["successes"] == 0


def test_stopping_early_changes_nothing(env):
    """The host loop stops once every episode has ended; the outcomes and final states are
    those of running every step (the frozen episodes do not change)."""
    program = protocol_a(env, A_CFG)
    early = run_one(program, TOWARD_DISK, jax.random.PRNGKey(3))
    rollouts = run_protocol(program, seed_acts(TOWARD_DISK), jnp.zeros(1),
                            jax.random.PRNGKey(3)[None], check_every=10 ** 6)
    full = jax.tree.map(lambda x: x[0], rollouts)
    assert int(early.steps.max()) < A_CFG.max_steps  # it did stop early
    for name in ("agent", "obj", "outcome", "steps", "idle"):
        np.testing.assert_array_equal(getattr(early, name), getattr(full, name))
