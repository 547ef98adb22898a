"""The lazy policy and the push task's evaluation protocols; re-evaluating a trained run."""

import json
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import PUSH
from lazyq_jax.run import RunDirError, evaluate_run, load_run
from lazyq_jax.tasks.base import CORRECT, NOT_PUSHED, WRONG, run_protocol, seed_acts
from lazyq_jax.tasks.push import EvalConfig
from lazyq_jax.tasks.push.protocols import protocol_a, protocol_b, summarize_a, summarize_b


def test_policy_pushes_from_behind_toward_the_goal(push_run):
    act = load_run(push_run).policy()
    goals = jnp.array([0.0, np.pi / 2, np.pi, -np.pi / 2])
    direction = np.stack([np.cos(goals), np.sin(goals)], 1)
    behind = jnp.asarray(-0.36 * direction, jnp.float32)  # finger on the far side from the goal
    action = np.asarray(act(jax.random.PRNGKey(0), behind, goals))
    np.testing.assert_allclose(np.linalg.norm(action, axis=1), 0.1, rtol=1e-5)
    cos = np.sum(action * direction, axis=1) / 0.1
    assert np.all(cos > 0.7), cos


def test_results_schema_determinism_and_figures(push_run):
    first = evaluate_run(push_run, progress=False)
    saved = json.loads((push_run / "lazy" / "eval.json").read_text())
    assert saved["block"] == PUSH.train.cycles and saved["seeds"] == [PUSH.seed]
    result = saved["per_seed"][0]
    a, b = result["protocol_a"], result["protocol_b"]
    assert len(a["per_goal"]) == PUSH.eval.n_directions
    for row in a["per_goal"]:
        assert set(row) == {"goal", "correct", "wrong", "not_pushed"}
        assert row["correct"] + row["wrong"] + row["not_pushed"] == PUSH.eval.episodes_per_direction
    assert 0 <= a["axis_correct_rate"] <= 1 and 0 <= a["overall_correct_rate"] <= 1
    assert b["rollouts"] == PUSH.eval.long_rollouts and 0 <= b["successes"] <= b["rollouts"]
    assert result["seed"] == PUSH.seed and result["eval_seed"] == PUSH.seed + PUSH.eval.seed
    for name in ("fig3_value.png", "fig4_outcomes.png", "fig5_long_horizon.png"):
        path = push_run / "figures" / "lazy" / name
        assert path.stat().st_size > 10_000 and path.read_bytes()[:4] == b"\x89PNG"
    gif = push_run / "figures" / "lazy" / "rollouts.gif"
    assert gif.read_bytes()[:6] == b"GIF89a" and gif.stat().st_size > 10_000
    again = evaluate_run(push_run, figures=False, progress=False)
    assert again["methods"]["lazy"]["per_seed"] == first["methods"]["lazy"]["per_seed"]
    other = evaluate_run(push_run, figures=False, progress=False, overrides=["eval.seed=5"])
    assert json.loads((push_run / "lazy" / "eval.json").read_text())["per_seed"][0]["eval_seed"] == \
        PUSH.seed + 5
    assert other["methods"]["lazy"]["per_seed"] != first["methods"]["lazy"]["per_seed"]


def test_evaluation_refuses_a_directory_without_a_run(tmp_path):
    with pytest.raises(RunDirError, match="no run here"):
        evaluate_run(tmp_path)
    out = subprocess.run([sys.executable, "-m", "lazyq_jax", "evaluate", "--run-dir", str(tmp_path)],
                         capture_output=True, text=True, timeout=120)
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
