"""OGBench's goal sampling in JAX (lazyq_jax.agents.goals) against GCDataset's distribution,
and the goal-conditioned agents drawing from trajectories through the runner's block."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lazyq_jax import agents
from lazyq_jax.agents import Problem
from lazyq_jax.agents.goals import (
    ACTOR_GOALS,
    VALUE_GOALS,
    GoalMix,
    goal_batches,
    sample_goal_rows,
    uses_trajectories,
)
from lazyq_jax.config import ConfigError
from lazyq_jax.types import Transitions

N_TRAJ, LENGTH = 40, 250


def trajectories():
    """Rows whose state is their own index (x) and trajectory (y)."""
    n = N_TRAJ * LENGTH
    idx = np.arange(n)
    s = np.stack([idx, idx // LENGTH], -1).astype(np.float32)
    last = (idx // LENGTH + 1) * LENGTH - 1
    return Transitions(s=jnp.asarray(s), a=jnp.zeros((n, 2)), s_next=jnp.asarray(s + 1),
                       r=jnp.zeros(n), g=jnp.asarray(s), done=jnp.zeros(n, bool),
                       traj_last=jnp.asarray(last, jnp.int32)), last


@pytest.mark.parametrize("mix", [VALUE_GOALS, ACTOR_GOALS, GoalMix(0.3, 0.3, False)])
def test_goal_rows_follow_gcdataset(mix):
    data, last = trajectories()
    n = len(last)
    b = 200_000
    idx = jax.random.randint(jax.random.PRNGKey(1), (b,), 0, n)
    goal = np.asarray(sample_goal_rows(jax.random.PRNGKey(2), idx, data.traj_last, jnp.int32(n),
                                       mix, 0.99))
    idx = np.asarray(idx)
    final = last[idx]
    same_traj = (goal >= idx) & (goal <= final)
    cur = goal == idx
    tol = 5 * np.sqrt(0.25 / b)
    # the current state: p_cur, plus the trajectory draws that land on idx (at its last row)
    # and the random draws that hit it (1 / n)
    at_end = final == idx
    p_traj_eff = (1 - mix.p_cur) * mix.p_traj / (1 - mix.p_cur) if mix.p_cur < 1 else 0
    expect_cur = mix.p_cur + p_traj_eff * np.mean(at_end) + (1 - mix.p_cur - p_traj_eff) / n
    assert abs(cur.mean() - expect_cur) < tol
    # random goals: uniform over all rows, so outside the trajectory with prob 1 - L / n
    outside = ~same_traj
    expect_outside = (1 - mix.p_cur - p_traj_eff) * (1 - np.mean(np.minimum(final - idx + 1, n)) / n)
    assert abs(outside.mean() - expect_outside) < tol
    traj_rows = same_traj & ~cur
    off = (goal - idx)[traj_rows]
    assert (off >= 1).all()
    if mix.geom:  # rows > 100 from their end: P(Geom(0.01) > 100) = 0.99^100, no truncation
        far = (final - idx)[traj_rows] > 100
        assert abs(np.mean(off[far] > 100) - 0.99 ** 100) < 5 * np.sqrt(0.25 / far.sum())
    else:  # uniform between the next row and the last: the mean fraction of the way is 1/2
        frac = (off - 1) / np.maximum((final - idx)[traj_rows] - 1, 1)
        assert abs(frac.mean() - 0.5) < 0.01


def test_goal_batches_reward_success_and_goals():
    data, _ = trajectories()
    idx = jnp.arange(0, len(data.r), 7)
    value, actor = goal_batches(data, idx, jax.random.PRNGKey(3), jnp.int32(len(data.r)), 0.99)
    g_v, g_a = np.asarray(value.g[:, 0]).astype(int), np.asarray(actor.g[:, 0]).astype(int)
    success = g_v == np.asarray(idx)
    np.testing.assert_array_equal(np.asarray(value.done), success)
    np.testing.assert_array_equal(np.asarray(value.r), success.astype(np.float32) - 1)
    assert 0.15 < success.mean() < 0.3
    # actor goals: later rows of the same trajectory (or the row itself at the end)
    np.testing.assert_array_equal(np.asarray(actor.g[:, 1]), np.asarray(actor.s[:, 1]))
    assert (g_a >= np.asarray(idx)).all()
    np.testing.assert_array_equal(np.asarray(actor.a), np.asarray(data.a[idx]))


def test_trajectory_goals_need_trajectories_and_state_goals():
    data, _ = trajectories()
    assert uses_trajectories("auto", data, "x") and not uses_trajectories("rows", data, "x")
    plain = data.replace(traj_last=None)
    assert not uses_trajectories("auto", plain, "x")
    with pytest.raises(ValueError, match="needs trajectory data"):
        uses_trajectories("trajectories", plain, "x")
    with pytest.raises(ValueError, match="are states"):
        uses_trajectories("auto", data.replace(g=data.g[:, :1]), "x")
    with pytest.raises(ConfigError, match="goals"):
        agents.GCIVLConfig(goals="future")


@pytest.mark.parametrize("name", ["gcivl", "gciql", "gcbc"])
def test_agents_train_on_trajectory_goals(name):
    """A block on trajectory data runs under jit (the fresh goals inside the step)."""
    data, _ = trajectories()
    cls = agents.config_class(name)
    agent = agents.make(name, cls(steps=3, blocks=1, width=8, depth=2, batch_size=16),
                        problem=Problem(action_length=1.0, action_set="box"))
    state = agent.init(jax.random.PRNGKey(0), data)
    state, metrics = jax.jit(lambda st: agent.run_block(st, data))(state)
    assert int(metrics["steps"]) == 3
    assert all(np.isfinite(np.asarray(v)).all() for v in jax.tree.leaves(metrics))
