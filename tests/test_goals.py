"""OGBench's goal sampling in JAX (lazyq_jax.agents.goals) against GCDataset's distribution,
and the goal-conditioned agents drawing from trajectories through the runner's block."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lazyq_jax import agents
from lazyq_jax.agents import Problem, lazy
from lazyq_jax.agents.goals import (
    ACTOR_GOALS,
    VALUE_GOALS,
    GoalMix,
    goal_batches,
    sample_goal_rows,
    uses_trajectories,
)
from lazyq_jax.config import ConfigError, NeighbourConfig, TrainConfig
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


@pytest.mark.parametrize("name", ["gcivl", "gciql", "gcbc", "qrl", "crl", "hiql"])
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


def test_lazy_relabel_every_draws_fresh_goals_per_period():
    """``train.relabel_every``: the first period keeps the rows' own goals (the plain agent's
    neighbourhoods bitwise); later periods draw every row an OGBench value goal from its
    trajectory (the same draw within a period, a new one in the next), with its reward, and
    the neighbourhoods of those goals; the block trains on them."""
    n_traj, length = 10, 50
    n = n_traj * length
    idx = np.arange(n)
    s = np.stack([idx, idx // length], -1).astype(np.float32)
    data = Transitions(s=jnp.asarray(s), a=jnp.asarray(np.random.default_rng(0).uniform(-1, 1, (n, 2)),
                                                       jnp.float32),
                       s_next=jnp.asarray(s + 1), r=-jnp.ones(n), g=jnp.asarray(s[::-1].copy()),
                       done=jnp.zeros(n, bool),
                       traj_last=jnp.asarray((idx // length + 1) * length - 1, jnp.int32))
    nc = NeighbourConfig(k=4, radius_s=2.0, radius_g=3.0, local_model="action")

    def make(every):
        return lazy.make(lazy.LazyConfig(train=TrainConfig(cycles=7, width=8, depth=2, batch_size=100,
                                                           gamma=0.99, relabel_every=every),
                                         neighbours=nc), Problem(action_length=1.0, action_set="box"))

    agent, plain = make(3), make(0)
    assert [agent.refresh(b) for b in range(7)] == [True, False, False, True, False, False, True]
    first, ref = agent.prepare(0, data, n, 0), plain.prepare(0, data, n, 0)
    np.testing.assert_array_equal(np.asarray(first.idx), np.asarray(ref.idx))
    np.testing.assert_array_equal(np.asarray(first.g), np.asarray(data.g))
    assert ref.g is None
    p3, p5, p6 = (agent.prepare(0, data, n, b) for b in (3, 5, 6))
    np.testing.assert_array_equal(np.asarray(p3.g), np.asarray(p5.g))
    assert np.mean(np.asarray(p3.g[:, 0]) != np.asarray(p6.g[:, 0])) > 0.5  # other goal rows
    for nb in (p3, p6):
        goal = np.asarray(nb.g[:, 0]).astype(int)  # the goal's row (the state is its index)
        np.testing.assert_array_equal(np.asarray(nb.g), s[goal])
        success = goal == idx
        np.testing.assert_array_equal(np.asarray(nb.done), success)
        np.testing.assert_array_equal(np.asarray(nb.r), success.astype(np.float32) - 1)
        assert abs(success.mean() - 0.2) < 0.1  # p_cur 0.2 (+ trajectory ends): 500 rows
        same_traj = (goal >= idx) & (goal // length == idx // length)
        assert 0.5 < same_traj.mean() < 0.85  # 0.2 + 0.5 + the random draws in the trajectory
        # the neighbourhoods are those of the fresh goals (the plain agent on relabelled data)
        fresh = data.replace(g=nb.g, r=nb.r, done=nb.done)
        np.testing.assert_array_equal(np.asarray(nb.idx), np.asarray(plain.prepare(0, fresh, n, 0).idx))
    state = agent.init(jax.random.PRNGKey(0), data)
    _, trained = agent.run_block(state, data, p3)
    _, on_fresh = plain.run_block(state, data.replace(g=p3.g, r=p3.r, done=p3.done),
                                  lazy.Neighbourhoods(p3.idx, p3.level))
    _, on_rows = plain.run_block(state, data, lazy.Neighbourhoods(p3.idx, p3.level))
    assert float(trained["loss"]) == float(on_fresh["loss"]) != float(on_rows["loss"])
    with pytest.raises(ValueError, match="relabel_every"):
        agent.init(jax.random.PRNGKey(0), data.replace(traj_last=None))
    with pytest.raises(ConfigError, match="relabel_every"):
        TrainConfig(relabel_every=-1)
