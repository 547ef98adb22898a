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
    actor_goals,
    goal_batches,
    minibatches,
    sample_goal_rows,
    sample_goal_rows_and_random,
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


def ogbench_sample_goals(idxs, terminal_locs, p_curgoal, p_trajgoal, p_randomgoal, geom_sample,
                         discount, random_goal_idxs, offsets, distances, u_traj, u_cur):
    """OGBench's ``GCDataset.sample_goals`` (``impls/utils/datasets.py``) line for line, its
    ``np.random`` draws given (``random_goal_idxs``: ``get_random_idxs``; ``offsets``: the
    geometric ones; ``distances``, ``u_traj``, ``u_cur``: its three ``np.random.rand``), and
    the uniform offsets in float32 (our draws' precision; OGBench's are float64)."""
    assert np.isclose(p_curgoal + p_trajgoal + p_randomgoal, 1.0)
    final_state_idxs = terminal_locs[np.searchsorted(terminal_locs, idxs)]
    if geom_sample:
        traj_goal_idxs = np.minimum(idxs + offsets, final_state_idxs)
    else:
        f32 = np.float32
        traj_goal_idxs = np.round(
            np.minimum(idxs + 1, final_state_idxs).astype(f32) * distances
            + final_state_idxs.astype(f32) * (f32(1) - distances)
        ).astype(int)
    if p_curgoal == 1.0:
        goal_idxs = idxs
    else:
        goal_idxs = np.where(u_traj < p_trajgoal / (1.0 - p_curgoal), traj_goal_idxs, random_goal_idxs)
        goal_idxs = np.where(u_cur < p_curgoal, idxs, goal_idxs)
    return goal_idxs


def ogbench_draws(key, shape, n, discount):
    """The draws :func:`sample_goal_rows` makes from ``key`` (its four keys), for
    :func:`ogbench_sample_goals`."""
    k_rand, k_off, k_traj, k_cur = jax.random.split(key, 4)
    return {"random_goal_idxs": np.asarray(jax.random.randint(k_rand, shape, 0, n)),
            "offsets": np.asarray(jax.random.geometric(k_off, 1.0 - discount, shape, dtype=jnp.int32)),
            "distances": np.asarray(jax.random.uniform(k_off, shape)),
            "u_traj": np.asarray(jax.random.uniform(k_traj, shape)),
            "u_cur": np.asarray(jax.random.uniform(k_cur, shape))}


def test_actor_goals_are_ogbenchs_actor_mixture():
    """``actor_goals(p)``: OGBench's ``actor_p_curgoal = 0``, ``actor_p_trajgoal = 1 - p``,
    ``actor_p_randomgoal = p``, uniform; 0 is the default mixture exactly."""
    assert actor_goals(0.0) == ACTOR_GOALS
    assert actor_goals(0.0).p_traj == 1.0 and actor_goals(0.0).p_cur == 0.0
    assert actor_goals(0.5) == GoalMix(p_cur=0.0, p_traj=0.5, geom=False)
    assert actor_goals(1.0) == GoalMix(p_cur=0.0, p_traj=0.0, geom=False)


@pytest.mark.parametrize("mix, p_random", [(actor_goals(0.5), 0.5), (actor_goals(0.0), 0.0),
                                           (VALUE_GOALS, 0.3), (GoalMix(0.3, 0.3, False), 0.4)])
def test_goal_rows_equal_ogbench_sample_goals_given_its_draws(mix, p_random):
    """OGBench's ``sample_goals`` (:func:`ogbench_sample_goals`) fed the draws our
    :func:`sample_goal_rows` makes gives its goals exactly (the stitch actor goals
    ``(p_cur, p_traj, p_random) = (0, 0.5, 0.5)`` among them); the random flag marks the rows
    that took OGBench's ``random_goal_idxs``."""
    lengths = [7, 12, 5]  # three hand-made trajectories
    last = np.repeat(np.cumsum(lengths) - 1, lengths)
    n = len(last)
    terminal_locs = np.cumsum(lengths) - 1
    idx = jax.random.randint(jax.random.PRNGKey(4), (4000,), 0, n)
    key, discount = jax.random.PRNGKey(5), 0.9
    goal, random = sample_goal_rows_and_random(key, idx, jnp.asarray(last, jnp.int32), jnp.int32(n),
                                               mix, discount)
    draws = ogbench_draws(key, idx.shape, n, discount)
    want = ogbench_sample_goals(np.asarray(idx), terminal_locs, mix.p_cur, mix.p_traj, p_random,
                                mix.geom, discount, **draws)
    np.testing.assert_array_equal(np.asarray(goal), want)
    np.testing.assert_array_equal(np.asarray(sample_goal_rows(key, idx, jnp.asarray(last, jnp.int32),
                                                              jnp.int32(n), mix, discount)), want)
    took_random = ~(draws["u_cur"] < mix.p_cur) & ~(draws["u_traj"] < mix.p_traj / (1 - mix.p_cur))
    np.testing.assert_array_equal(np.asarray(random), took_random)
    np.testing.assert_array_equal(want[took_random], draws["random_goal_idxs"][took_random])


def test_stitch_actor_goals_frequencies():
    """Actor goals with ``actor_p_randomgoal = 0.5``: half the rows a random row (uniform over
    all rows), half a later row of their trajectory; the share of goals in the row's own
    future ``[idx, last]`` is ``0.5 + 0.5 E[(last - idx + 1) / n]``, as for OGBench's
    ``sample_goals`` with NumPy's generator on the same rows (5 binomial sigmas of 200,000)."""
    data, last = trajectories()
    n, b, p = len(last), 200_000, 0.5
    idx = jax.random.randint(jax.random.PRNGKey(1), (b,), 0, n)
    goal, random = sample_goal_rows_and_random(jax.random.PRNGKey(2), idx, data.traj_last,
                                               jnp.int32(n), actor_goals(p), 0.99)
    goal, random, idx = np.asarray(goal), np.asarray(random), np.asarray(idx)
    final = last[idx]
    sigma = lambda q, m: 5 * np.sqrt(q * (1 - q) / m)
    assert abs(random.mean() - p) < sigma(p, b)
    # the trajectory goals: in (idx, last] (idx itself at the last row), uniformly
    traj = ~random
    assert ((goal[traj] >= np.minimum(idx[traj] + 1, final[traj])) & (goal[traj] <= final[traj])).all()
    # the random goals: uniform over the rows (each tenth of them holds a tenth)
    tenth = goal[random] * 10 // n
    m = random.sum()
    assert all(abs(np.mean(tenth == i) - 0.1) < sigma(0.1, m) for i in range(10))
    expect_future = (1 - p) + p * np.mean(final - idx + 1) / n
    rng = np.random.default_rng(0)
    terminal_locs = np.unique(last)
    ours = np.mean((goal >= idx) & (goal <= final))
    theirs = ogbench_sample_goals(
        idx, terminal_locs, 0.0, 1 - p, p, False, 0.99, random_goal_idxs=rng.integers(0, n, b),
        offsets=None, distances=rng.random(b).astype(np.float32), u_traj=rng.random(b), u_cur=rng.random(b))
    theirs = np.mean((theirs >= idx) & (theirs <= final))
    for got in (ours, theirs):
        assert abs(got - expect_future) < sigma(expect_future, b)


def test_random_actor_goals_need_trajectories():
    """Random actor goals come from the trajectories: on the rows' own goals they are an error,
    the default mixture is not."""
    data, _ = trajectories()
    plain = data.replace(traj_last=None)
    idx, key = jnp.arange(8), jax.random.PRNGKey(0)
    _, actor = minibatches("auto", plain, idx, key, jnp.int32(8), 0.99, "x")
    np.testing.assert_array_equal(np.asarray(actor.g), np.asarray(plain.g[:8]))
    with pytest.raises(ValueError, match="actor_p_randomgoal = 0.5.*set actor_p_randomgoal=0"):
        minibatches("auto", plain, idx, key, jnp.int32(8), 0.99, "x", actor=actor_goals(0.5))
    with pytest.raises(ValueError, match="actor_p_randomgoal"):
        minibatches("rows", data, idx, key, jnp.int32(8), 0.99, "x", actor=actor_goals(0.5))
    _, actor = minibatches("auto", data, idx, key, jnp.int32(8), 0.99, "x", actor=actor_goals(0.5))
    assert actor.g.shape == data.g[:8].shape


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
