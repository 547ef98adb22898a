"""``train.target_steps``: lazy Q's targets from each neighbour's multi-step return along its
own trajectory (:func:`lazyq_jax.targets.multi_step_transitions`): the paths against a
Python walk over the rows, the cycle's targets against the public pieces put together by
hand, a corridor whose optimal values are known, and the data and settings it refuses."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lazyq_jax import agents
from lazyq_jax.agents import gcivl
from lazyq_jax.agents.base import Problem
from lazyq_jax.config import ConfigError, NeighbourConfig, TrainConfig
from lazyq_jax.targets import lazy_target, local_fits, multi_step_transitions
from lazyq_jax.train import make_train
from lazyq_jax.types import Transitions, pad_transitions

GAMMA = 0.9


def _relabelled(lengths=(1, 2, 5, 9, 13, 4), seed=0):
    """Random walks one after the other (``traj_last``), relabelled as OGBench's rows: each
    row's goal is its own state (terminal, ``r = 0``), a later state of its trajectory, or
    a random state; ``r = -1`` otherwise."""
    rng = np.random.default_rng(seed)
    s, s_next, last = [], [], []
    for n_t in lengths:
        walk = np.cumsum(rng.normal(0, 0.2, (n_t + 1, 2)), 0).astype(np.float32)
        s.append(walk[:-1])
        s_next.append(walk[1:])
        last += [len(last) + n_t - 1] * n_t
    s, s_next, last = np.concatenate(s), np.concatenate(s_next), np.asarray(last, np.int32)
    n = len(s)
    rows = np.arange(n)
    kind = rng.integers(0, 3, n)
    later = np.minimum(rows + rng.integers(1, 12, n), last)
    goal_row = np.where(kind == 0, rows, np.where(kind == 1, later, rng.integers(0, n, n)))
    done = goal_row == rows
    a = rng.uniform(-1, 1, (n, 2)).astype(np.float32)
    return Transitions(s=jnp.asarray(s), a=jnp.asarray(a), s_next=jnp.asarray(s_next),
                       r=jnp.asarray(done.astype(np.float32) - 1.0), g=jnp.asarray(s[goal_row]),
                       done=jnp.asarray(done), traj_last=jnp.asarray(last))


def _walk(data, steps, gamma):
    """The reference: each row's path walked in Python, in float64."""
    s_next, g, last = np.asarray(data.s_next), np.asarray(data.g), np.asarray(data.traj_last)
    r, done = np.asarray(data.r, np.float64), np.asarray(data.done)
    out_s, out_r, out_d = s_next.copy(), r.copy(), np.full(len(r), gamma)
    for j in range(len(r)):
        if done[j]:
            continue
        ret = 0.0
        for t in range(1, steps + 1):
            ret += gamma ** (t - 1) * r[j]
            if j + t - 1 == last[j] or np.array_equal(s_next[j + t - 1], g[j]) or t == steps:
                out_s[j], out_r[j], out_d[j] = s_next[j + t - 1], ret, gamma ** t
                break
    return out_s, out_r, out_d


@pytest.mark.parametrize("steps", [2, 4, 11])
def test_paths_equal_a_python_walk(steps):
    """Every row's ``h``-step next state, return and discount: stopped at the goal's state, at
    the trajectory's end or after ``steps``; terminal rows as they are; with padded rows
    appended, the valid rows' results unchanged and the padding's ``h = 1``."""
    data = _relabelled()
    assert np.asarray(data.done).any() and not np.asarray(data.done).all()
    want_s, want_r, want_d = _walk(data, steps, GAMMA)
    got, disc = jax.jit(lambda d: multi_step_transitions(d, steps, GAMMA))(data)
    np.testing.assert_array_equal(got.s_next, want_s)  # gathered, not computed
    # float32 powers and a geometric sum of <= 11 terms of size 1: a few ulps of 10
    np.testing.assert_allclose(got.r, want_r, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(disc, want_d, rtol=1e-6)
    for name in ("s", "a", "g", "done", "traj_last"):
        np.testing.assert_array_equal(getattr(got, name), getattr(data, name))
    # the paths really differ from the one-step rows (else this test could not fail)
    assert np.sum(np.abs(want_d - GAMMA) > 1e-9) > len(want_d) // 3
    padded, pdisc = multi_step_transitions(pad_transitions(data, data.size + 7), steps, GAMMA)
    np.testing.assert_array_equal(padded.s_next[: data.size], got.s_next)
    np.testing.assert_array_equal(pdisc[: data.size], disc)
    np.testing.assert_array_equal(pdisc[data.size:], np.float32(GAMMA))
    np.testing.assert_array_equal(padded.s_next[data.size:], 0.0)


def test_one_step_rows_are_the_data_bit_for_bit():
    """``steps = 1`` returns the data and the scalar discount; a row whose path has one step
    gets exactly its own ``r`` and ``gamma`` (so the default changes nothing)."""
    data = _relabelled()
    same, gamma = multi_step_transitions(data, 1, GAMMA)
    assert same is data and gamma == GAMMA
    got, disc = multi_step_transitions(data, 5, GAMMA)
    last, rows = np.asarray(data.traj_last), np.arange(data.size)
    one = (last == rows) & ~np.asarray(data.done)  # the trajectory ends after this row
    assert one.sum() >= 3
    np.testing.assert_array_equal(np.asarray(got.r)[one], np.asarray(data.r)[one])
    np.testing.assert_array_equal(np.asarray(disc)[one], np.float32(GAMMA))


def test_the_cycles_targets_are_eq8_on_the_multi_step_brackets():
    """The trainer's targets with ``target_steps`` (their mean and spread) equal the public
    pieces put together by hand: the paths, the local fits with the per-row discount and
    Eq. (8); and they differ from the one-step targets."""
    data = _relabelled(lengths=(7, 9, 12, 8, 10, 6, 11, 9), seed=1)
    n, k = data.size, 6
    idx = jax.random.randint(jax.random.PRNGKey(2), (n, k), 0, n)
    base = TrainConfig(cycles=1, epochs=1, width=8, depth=3, batch_size=16, gamma=GAMMA)
    means = {}
    for steps in (1, 6):
        trainer = make_train(dataclasses.replace(base, target_steps=steps), 1.0,
                             action_set="box", state_offsets=True, goal_offsets=True)
        state = trainer.init(jax.random.PRNGKey(0), data)
        paths, disc = multi_step_transitions(data, steps, GAMMA)
        alpha, beta, y_nb = local_fits(trainer.value_fn(state), paths, idx, gamma=disc,
                                       state_offsets=True, goal_offsets=True)
        y, _ = lazy_target(alpha, beta, y_nb, 1.0, True, "box")
        _, metrics = jax.jit(trainer.run_cycle)(state, data, idx)
        # float32 means of n values of size ~5: a few 1e-7 relative
        np.testing.assert_allclose(float(metrics["target_mean"]), float(jnp.mean(y)), rtol=1e-5)
        np.testing.assert_allclose(float(metrics["target_std"]), float(jnp.std(y)), rtol=1e-4)
        means[steps] = float(jnp.mean(y))
    assert abs(means[6] - means[1]) > 0.1, means  # the multi-step brackets are other numbers


def test_a_corridor_reaches_its_optimal_values():
    """A corridor walked straight to its end, relabelled with goals ahead: the ``h``-step
    bracket of the optimal ``V*(s, g) = -(1 - gamma^d) / (1 - gamma)`` (``d`` steps to the
    goal) is ``V*`` itself on every row, with any number of steps; a wrong V is not a fixed
    point."""
    length, n_traj = 12, 3
    x = np.arange(length + 1, dtype=np.float32)
    s = np.tile(np.stack([x[:-1], np.zeros(length, np.float32)], 1), (n_traj, 1))
    s_next = np.tile(np.stack([x[1:], np.zeros(length, np.float32)], 1), (n_traj, 1))
    rows = np.arange(len(s))
    last = (rows // length * length + length - 1).astype(np.int32)
    rng = np.random.default_rng(0)
    goal_row = np.minimum(rows + rng.integers(0, 9, len(s)), last)
    done = goal_row == rows
    data = Transitions(s=jnp.asarray(s), a=jnp.ones((len(s), 1)), s_next=jnp.asarray(s_next),
                       r=jnp.asarray(done.astype(np.float32) - 1.0), g=jnp.asarray(s[goal_row]),
                       done=jnp.asarray(done), traj_last=jnp.asarray(last))

    def v_star(s, g):  # d = steps to the goal along the corridor
        d = jnp.abs(g[:, 0] - s[:, 0])
        return -(1.0 - GAMMA ** d) / (1.0 - GAMMA)

    want = np.asarray(v_star(data.s, data.g))
    for steps in (1, 3, 8):
        paths, disc = multi_step_transitions(data, steps, GAMMA)
        y = paths.r + disc * jnp.where(paths.done, 0.0, v_star(paths.s_next, paths.g))
        np.testing.assert_allclose(y, want, rtol=1e-5, atol=1e-5)  # float32 powers of 0.9
        wrong = paths.r + disc * jnp.where(paths.done, 0.0, v_star(paths.s_next, paths.g) + 1.0)
        assert np.max(np.abs(np.asarray(wrong) - want)) > 0.5


def test_settings_and_data_it_refuses():
    with pytest.raises(ConfigError, match="target_steps must be an integer >= 1"):
        TrainConfig(target_steps=0)
    with pytest.raises(ConfigError, match="bootstrap_goal must stay 'neighbour'; set train.target_steps=1"):
        make_train(TrainConfig(target_steps=3, bootstrap_goal="row"), 1.0)
    maze = Problem(action_length=1.0, action_set="box", state_goal_reward=True)
    cfg = agents.LazyConfig(train=TrainConfig(target_steps=3, width=8, depth=2),
                            neighbours=NeighbourConfig(k=6, local_model="action+state"))
    agent = agents.make("lazy", cfg, problem=maze)
    data = _relabelled()
    with pytest.raises(ConfigError, match="have none"):
        agent.init(jax.random.PRNGKey(0), data.replace(traj_last=None))
    with pytest.raises(ConfigError, match="goals must be states"):
        agent.init(jax.random.PRNGKey(0), data.replace(g=data.g[:, 0]))
    agent.init(jax.random.PRNGKey(0), data)  # trajectories with state goals: accepted
    agent.check_target_steps(data, data.size)
    off = data.replace(done=data.done.at[1].set(True))  # row 1's goal is not its state
    assert not np.array_equal(np.asarray(data.s[1]), np.asarray(data.g[1]))
    with pytest.raises(ConfigError, match="row 1 is terminal"):
        agent.check_target_steps(off, data.size)
    with pytest.raises(ConfigError, match="one reward for every step"):
        agent.check_target_steps(data.replace(r=data.r.at[1].set(-2.0)), data.size)
    agent.check_target_steps(data.replace(r=data.r.at[1].set(-2.0)), 1)  # rows past n_valid: not read


def test_gcivl_control_takes_the_paths_to_its_fresh_goals():
    """GCIVL's ``target_steps`` (a control for lazy Q's option): the value rows' next states,
    returns and discounts are their paths to the goals drawn for them (against the Python
    walk), the actor rows stay one-step, the value loss reads the per-row discount (against
    ``ivl_value_loss`` with it), and one training block runs; data without trajectories are
    refused."""
    data = _relabelled(lengths=(7, 9, 12, 8, 10, 6, 11, 9), seed=3)
    problem = Problem(action_length=1.0, action_set="box", state_goal_reward=True)
    cfg = gcivl.GCIVLConfig(steps=4, batch_size=32, width=8, depth=2, blocks=2, target_steps=6)
    agent = gcivl.make(cfg, problem)
    rows = jax.random.randint(jax.random.PRNGKey(4), (32,), 0, data.size)
    value, actor, disc = agent.batch(data, rows, jax.random.PRNGKey(5), jnp.int32(data.size))
    one_value, one_actor = gcivl.make(dataclasses.replace(cfg, target_steps=1), problem).batch(
        data, rows, jax.random.PRNGKey(5), jnp.int32(data.size))
    for name in ("s", "g", "done", "a"):  # the same goals drawn, only the paths added
        np.testing.assert_array_equal(getattr(value, name), getattr(one_value, name))
    np.testing.assert_array_equal(actor.s_next, one_actor.s_next)
    picked = Transitions(s=data.s, a=data.a, s_next=data.s_next, r=data.r, g=data.g, done=data.done,
                         traj_last=data.traj_last)
    for i, j in enumerate(np.asarray(rows)):  # each row walked with its drawn goal
        one = picked.replace(g=picked.g.at[j].set(value.g[i]), r=picked.r.at[j].set(one_value.r[i]),
                             done=picked.done.at[j].set(one_value.done[i]))
        want_s, want_r, want_d = _walk(one, 6, cfg.gamma)
        np.testing.assert_array_equal(value.s_next[i], want_s[j])
        np.testing.assert_allclose(value.r[i], want_r[j], rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(disc[i], want_d[j], rtol=1e-6)
    assert np.sum(np.abs(np.asarray(disc) - cfg.gamma) > 1e-6) > 8  # paths longer than one step
    state = agent.init(jax.random.PRNGKey(0), data)
    params, target = state.model["params"], state.model["target_value"]
    loss, _ = agent.value_loss(params, target, value, disc)
    want, _ = gcivl.ivl_value_loss(agent.values(target, value.s_next, value.g), agent.values(target, value.s, value.g),
                                   agent.values(params["value"], value.s, value.g), value, disc, cfg.expectile)
    np.testing.assert_allclose(loss, want, rtol=1e-6)
    state, metrics = jax.jit(agent.run_block)(state, data)
    assert np.all(np.isfinite(np.asarray(metrics["value_loss"])))
    with pytest.raises(ConfigError, match="target_steps=6 follows each row's trajectory"):
        agent.batch(data.replace(traj_last=None), rows, jax.random.PRNGKey(5), jnp.int32(data.size))
