"""The lazy policy and the evaluation protocols on a small trained run."""

import json
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import PUSH
from lazyq_jax.config import EvalConfig
from lazyq_jax.evaluate import (CORRECT, NOT_PUSHED, WRONG, EvalError, evaluate_run, protocol_a,
                                protocol_b, summarize_a, summarize_b)
from lazyq_jax.policy import lazy_policy, make_lazy_policy


def test_policy_pushes_from_behind_toward_the_goal(push_run):
    _, state, trainer, data = push_run
    nc = PUSH.neighbours
    policy = make_lazy_policy(trainer.value_fn(state), data, gamma=PUSH.train.gamma,
                              action_length=0.1, k=nc.k, radius_s=nc.radius_s,
                              radius_g=nc.radius_g, growth=nc.growth, max_level=4)
    goals = jnp.array([0.0, np.pi / 2, np.pi, -np.pi / 2])
    direction = np.stack([np.cos(goals), np.sin(goals)], 1)
    behind = jnp.asarray(-0.36 * direction, jnp.float32)  # finger on the far side from the goal
    action, beta, found = jax.jit(lazy_policy)(policy, jax.random.PRNGKey(0), behind, goals)
    action = np.asarray(action)
    assert np.all(np.asarray(found))
    np.testing.assert_allclose(np.linalg.norm(action, axis=1), 0.1, rtol=1e-5)
    cos = np.sum(action * direction, axis=1) / 0.1
    assert np.all(cos > 0.7), cos


def test_results_schema_determinism_and_figures(push_run):
    run_dir = push_run[0]
    first = evaluate_run(run_dir)
    saved = json.loads((run_dir / "eval" / "results.json").read_text())
    a, b = saved["protocol_a"], saved["protocol_b"]
    assert len(a["per_goal"]) == PUSH.eval.n_directions
    for row in a["per_goal"]:
        assert set(row) == {"goal", "correct", "wrong", "not_pushed"}
        assert row["correct"] + row["wrong"] + row["not_pushed"] == PUSH.eval.episodes_per_direction
    assert 0 <= a["axis_correct_rate"] <= 1 and 0 <= a["overall_correct_rate"] <= 1
    assert b["rollouts"] == PUSH.eval.long_rollouts and 0 <= b["successes"] <= b["rollouts"]
    assert saved["seed"] == PUSH.eval.seed and saved["checkpoint"].endswith("/4")
    for name in ("fig3_value.png", "fig4_outcomes.png", "fig5_long_horizon.png"):
        path = run_dir / "figures" / name
        assert path.stat().st_size > 10_000 and path.read_bytes()[:4] == b"\x89PNG"
    again = evaluate_run(run_dir, figures=False)
    strip = lambda r: {k: v for k, v in r.items() if k != "seconds"}
    assert strip(again) == strip(first)


def test_evaluation_refuses_a_run_without_checkpoint(tmp_path):
    with pytest.raises(EvalError, match="no checkpoint"):
        evaluate_run(tmp_path)
    out = subprocess.run([sys.executable, "-m", "lazyq_jax", "evaluate", "--run-dir", str(tmp_path)],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode != 0 and "no checkpoint" in out.stderr


def scripted(fn):
    """A stand-in policy ``act(key, s, g)`` with a fixed rule (always 'found')."""
    return lambda key, s, g: (fn(s, g), jnp.ones(s.shape[0], bool))


A_CFG = EvalConfig(n_directions=8, episodes_per_direction=4, max_steps=12, start_range=0.6)


def test_protocol_a_starts_behind_and_classifies_pushes(env):
    toward_disk = scripted(lambda s, g: -s)
    r = jax.device_get(jax.jit(lambda k: protocol_a(env, toward_disk, k, A_CFG))(jax.random.PRNGKey(0)))
    goals = np.repeat(np.arange(8) * np.pi / 4, 4)
    direction = np.stack([np.cos(goals), np.sin(goals)], 1)
    start = r.finger[0]
    assert np.all(np.sum(start * direction, 1) < 0)  # behind the disk w.r.t. the goal
    assert np.all(np.linalg.norm(start, axis=1) > 0.31) and np.all(np.abs(start) <= 0.6)
    assert np.all(r.outcome != NOT_PUSHED)  # heading for the centre always hits the disk
    # Independent classification from the recorded trajectory: the disk only moves
    # in the episode's last (frozen) step, by the push that ended it.
    delta = r.disk[-1] - r.disk[0]
    cos = np.sum(delta * direction, 1) / np.linalg.norm(delta, axis=1)
    np.testing.assert_array_equal(r.outcome, np.where(cos >= 0.9, CORRECT, WRONG))
    assert {CORRECT, WRONG} <= set(r.outcome.tolist())  # both classes occur
    summary = summarize_a(r, A_CFG)
    assert sum(row["correct"] for row in summary["per_goal"]) == int(np.sum(r.outcome == CORRECT))


def test_a_policy_that_does_not_move_never_pushes(env):
    still = scripted(lambda s, g: jnp.zeros_like(s))
    r = jax.jit(lambda k: protocol_a(env, still, k, A_CFG))(jax.random.PRNGKey(1))
    assert np.all(np.asarray(r.outcome) == NOT_PUSHED)
    assert np.all(np.asarray(r.steps) == A_CFG.max_steps)


def test_protocol_b_success_at_start_and_out_of_time(env):
    still = scripted(lambda s, g: jnp.zeros_like(s))
    everywhere = EvalConfig(long_rollouts=6, long_max_steps=5, success_radius=5.0)
    r, _ = jax.jit(lambda k: protocol_b(env, still, k, everywhere, 0.75))(jax.random.PRNGKey(2))
    assert np.all(np.asarray(r.outcome) == CORRECT) and np.all(np.asarray(r.steps) == 0)
    tight = EvalConfig(long_rollouts=6, long_max_steps=5, success_radius=1e-4)
    r, target = jax.jit(lambda k: protocol_b(env, still, k, tight, 0.75))(jax.random.PRNGKey(2))
    assert np.all(np.asarray(r.outcome) == NOT_PUSHED) and np.all(np.asarray(r.steps) == 5)
    summary = summarize_b(r)
    assert summary["out_of_time"] == 6 and summary["successes"] == 0
