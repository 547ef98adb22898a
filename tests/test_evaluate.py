"""The lazy policy and the evaluation protocols on a small trained run."""

import json
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import PUSH
from lazyq_jax.evaluate import EvalError, evaluate_run
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
