"""``neighbours.subgoal_steps``: the lazy policy's two-level step (``lazy_subgoals``): the
subgoal among the neighbours' trajectories against a NumPy brute force, the low level as
Eq. (9)'s step towards it, the three levels of ``far_subgoal_steps``, the data it needs, the one-level step through the CLI and
``evaluate --set`` switching a trained run's step."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import POINTMAZE_SMOKE, cli, pointmaze_round_trip

from lazyq_jax import agents, tasks
from lazyq_jax.agents.base import Problem
from lazyq_jax.config import ConfigError, NeighbourConfig
from lazyq_jax.neighbours.query import query_policy
from lazyq_jax.policy import LazyPolicy, lazy_policy, lazy_subgoals, policy_index
from lazyq_jax.types import Transitions

STEP, H, K = 0.2, 4, 8


def value(s, g):  # a V(s, g) that is not linear: minus the distance
    return -jnp.sqrt(jnp.sum((s - g) ** 2, axis=-1) + 1e-12)


def _trajectories(n_traj=30, length=12, seed=0):
    """``n_traj`` random walks ``s' = s + STEP a`` of ``length`` steps in the unit square's
    neighbourhood, one after the other (``traj_last``: each row's trajectory's last row);
    the goals are states."""
    rng = np.random.default_rng(seed)
    a = rng.uniform(-1, 1, (n_traj, length, 2)).astype(np.float32)
    start = rng.uniform(-1, 1, (n_traj, 1, 2)).astype(np.float32)
    s = start + STEP * np.concatenate([np.zeros((n_traj, 1, 2), np.float32), np.cumsum(a, 1)[:, :-1]], 1)
    s_next = s + STEP * a
    n = n_traj * length
    last = np.repeat(np.arange(1, n_traj + 1) * length - 1, length).astype(np.int32)
    g = rng.uniform(-1, 1, (n, 2)).astype(np.float32)
    return Transitions(s=jnp.asarray(s.reshape(n, 2)), a=jnp.asarray(a.reshape(n, 2)),
                       r=jnp.full(n, -1.0), s_next=jnp.asarray(s_next.reshape(n, 2)), g=jnp.asarray(g),
                       done=jnp.zeros(n, bool), traj_last=jnp.asarray(last))


def _policy(data, steps=H, action_set="ball"):
    index = policy_index(np.asarray(data.s), None, k=K, radius_s=0.3, radius_g=1.0, growth=2 ** (1 / 3),
                         max_level=6)
    return LazyPolicy(index, data.a, jnp.zeros(data.size), jnp.float32(1.0), action_set, states=data.s,
                      next_states=data.s_next, value_vars={}, value_apply=lambda _, s, g: value(s, g),
                      subgoal_steps=steps, traj_last=data.traj_last)


def _queries(n=24, seed=3):
    rng = np.random.default_rng(seed)
    q = rng.uniform(-0.8, 0.8, (n, 2)).astype(np.float32)
    # half the goals far away, half within a step or two of the query
    far = rng.uniform(-1.5, 1.5, (n // 2, 2))
    near = q[n // 2:] + rng.normal(0, 0.1, (n - n // 2, 2))
    return jnp.asarray(q), jnp.asarray(np.concatenate([far, near]).astype(np.float32))


def test_subgoals_equal_a_numpy_brute_force():
    """The subgoal is the candidate ``s'[min(j + H - 1, last_j)]`` of the largest ``V(w_j, g)``
    over the query's neighbourhood, or ``g`` where ``V(s, g) >= mean_j V(s, w_j)``; both
    decisions against float64 NumPy (argmax compared by value: float32 may swap near-ties)."""
    data = _trajectories()
    policy = _policy(data)
    q, goals = _queries()
    key = jax.random.PRNGKey(1)
    nb = query_policy(policy.index, key, q, None)
    assert bool(jnp.all(nb.level >= 0))
    rows = jnp.maximum(nb.idx, 0)
    w = np.asarray(jax.jit(lazy_subgoals)(policy, rows, nb.idx >= 0, q, goals), np.float64)
    s2, last = np.asarray(data.s_next, np.float64), np.asarray(data.traj_last)
    qq, gg = np.asarray(q, np.float64), np.asarray(goals, np.float64)
    switched = decided = 0
    for b in range(len(qq)):
        r = np.asarray(nb.idx[b])
        cand = s2[np.minimum(r + H - 1, last[r])]
        v_cand = -np.linalg.norm(cand - gg[b], axis=1)
        margin = -np.linalg.norm(qq[b] - gg[b]) - np.mean(-np.linalg.norm(cand - qq[b], axis=1))
        if abs(margin) < 1e-4:  # too close to call in float32
            continue
        decided += 1
        if margin >= 0:
            switched += 1
            np.testing.assert_array_equal(w[b], gg[b])
        else:
            assert np.any(np.all(np.abs(cand - w[b]) < 1e-6, axis=1)), "the subgoal is not a candidate"
            assert -np.linalg.norm(w[b] - gg[b]) >= v_cand.max() - 1e-5
    assert decided >= 20 and 0 < switched < decided  # both branches were exercised


def test_the_low_level_is_the_greedy_step_towards_the_subgoal():
    """With ``subgoal_steps`` the action is Eq. (9)'s step of the same neighbourhood with the
    neighbours valued at the subgoal: the one-level policy asked for the goal ``w``."""
    data = _trajectories(seed=4)
    two = _policy(data)
    one = two.replace(subgoal_steps=0)
    q, goals = _queries(seed=5)
    key = jax.random.PRNGKey(7)
    nb = query_policy(two.index, key, q, None)
    w = lazy_subgoals(two, jnp.maximum(nb.idx, 0), nb.idx >= 0, q, goals)
    a2, b2, found = jax.jit(lazy_policy)(two, key, q, goals)
    a1, b1, _ = jax.jit(lazy_policy)(one, key, q, w)
    assert bool(jnp.all(found))
    # the same inputs to the same fit: beta to float32 rounding of its size; the direction
    # (the ball's greedy action) wherever beta is not near zero
    np.testing.assert_allclose(np.asarray(b2), np.asarray(b1), rtol=1e-4, atol=1e-4 * float(jnp.abs(b1).max()))
    big = np.asarray(jnp.linalg.norm(b1, axis=1)) > 1e-2 * float(jnp.abs(b1).max())
    np.testing.assert_allclose(np.asarray(a2)[big], np.asarray(a1)[big], atol=1e-3)
    # and it is not the step towards the goal itself (the subgoals differ from the goals)
    a0, _, _ = jax.jit(lazy_policy)(one, key, q, goals)
    assert float(jnp.max(jnp.abs(a0 - a2))) > 0.1


def test_the_far_level_picks_the_near_subgoals_goal():
    """``far_subgoal_steps = F``: the near subgoal is the two-level one asked for the far
    subgoal, which is the two-level subgoal of horizon F (each level against the brute-force
    tested ``lazy_subgoals``), and the action is the step towards the near one."""
    data = _trajectories(seed=6)
    three = _policy(data).replace(far_subgoal_steps=3 * H)
    q, goals = _queries(seed=7)
    key = jax.random.PRNGKey(2)
    nb = query_policy(three.index, key, q, None)
    rows, valid = jnp.maximum(nb.idx, 0), nb.idx >= 0
    far = lazy_subgoals(_policy(data, steps=3 * H), rows, valid, q, goals)
    near = lazy_subgoals(_policy(data), rows, valid, q, far)
    a3, b3, _ = jax.jit(lazy_policy)(three, key, q, goals)
    a1, b1, _ = jax.jit(lazy_policy)(_policy(data, steps=0), key, q, near)
    np.testing.assert_allclose(np.asarray(b3), np.asarray(b1), rtol=1e-4, atol=1e-4 * float(jnp.abs(b1).max()))
    # the far level changes the subgoals of some queries (else the test shows nothing)
    two = lazy_subgoals(_policy(data), rows, valid, q, goals)
    assert float(jnp.max(jnp.abs(near - two))) > 0.1
    with pytest.raises(ConfigError, match="far_subgoal_steps must be 0"):
        NeighbourConfig(subgoal_steps=25, far_subgoal_steps=25)
    with pytest.raises(ConfigError, match="far_subgoal_steps must be 0"):
        NeighbourConfig(subgoal_steps=150, far_subgoal_steps=100)
    # the one-level step has no subgoals: the far level is unused, the same step
    one = _policy(data, steps=0)
    np.testing.assert_array_equal(np.asarray(jax.jit(lazy_policy)(one.replace(far_subgoal_steps=3 * H), key, q, goals)[0]),
                                  np.asarray(jax.jit(lazy_policy)(one, key, q, goals)[0]))
    NeighbourConfig(subgoal_steps=0, far_subgoal_steps=100)  # accepted: evaluate --set subgoal_steps=0


def test_subgoals_need_trajectories_whose_goals_are_states():
    with pytest.raises(ConfigError, match="subgoal_steps"):
        NeighbourConfig(subgoal_steps=-1)
    maze = Problem(action_length=1.0, action_set="box", state_goal_reward=True)
    cfg = agents.LazyConfig(neighbours=NeighbourConfig(k=6, local_model="action+state", subgoal_steps=3))
    agent = agents.make("lazy", cfg, problem=maze)
    data = _trajectories(n_traj=4, length=5)
    with pytest.raises(ConfigError, match="trajectories"):
        agent.init(jax.random.PRNGKey(0), data.replace(traj_last=None))
    with pytest.raises(ConfigError, match="goals must be"):
        agent.init(jax.random.PRNGKey(0), data.replace(g=data.g[:, 0]))
    agent.init(jax.random.PRNGKey(0), data)  # trajectories with state goals: accepted


def test_the_one_level_step_and_evaluate_set_through_the_cli(tmp_path):
    """The two-level step is the maze's default (every pointmaze CLI test runs it); the
    paper's one-level step, with the tabulated values, at smoke scale: trained, evaluated,
    reloaded, acting.  Then ``evaluate --set neighbours.subgoal_steps=25`` on its
    checkpoint equals the run trained with the two-level step (the option changes acting
    only, so training is the same program on the same inputs), and the results name the
    setting; a plain ``evaluate`` gives the run's own policy back; settings of training
    are refused."""
    assert tasks.preset("pointmaze", "paper").neighbours.subgoal_steps == 25
    one, two = tmp_path / "one", tmp_path / "two"
    pointmaze_round_trip(one, "eval.max_steps=60", "neighbours.subgoal_steps=0")
    args = ["train", "--task", "pointmaze", "--preset", "smoke", "--run-dir", str(two), "--no-progress"]
    for a in [*POINTMAZE_SMOKE, "eval.max_steps=60"]:
        args += ["--set", a]
    out = cli(*args)
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-3000:]
    lazy = lambda d: json.loads((d / "results.json").read_text())["methods"]["lazy"]
    own, trained_two = lazy(one), lazy(two)
    assert own["per_seed"] != trained_two["per_seed"]  # the two policies act differently here
    quiet = ["--methods", "lazy", "--no-figures", "--no-progress"]
    out = cli("evaluate", "--run-dir", str(one), *quiet, "--set", "neighbours.subgoal_steps=25")
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-3000:]
    assert lazy(one)["per_seed"] == trained_two["per_seed"]
    assert lazy(one)["acting"] == {"neighbours.subgoal_steps": 25} and "acting" not in trained_two
    assert "| lazy (neighbours.subgoal_steps=25) |" in (one / "summary.md").read_text()
    assert json.loads((one / "lazy" / "eval.json").read_text())["acting"] == {"neighbours.subgoal_steps": 25}
    out = cli("evaluate", "--run-dir", str(one), *quiet)  # the run's own policy again
    assert out.returncode == 0 and lazy(one) == {**own, "timings": lazy(one)["timings"]}
    bad = cli("evaluate", "--run-dir", str(one), *quiet, "--set", "train.lr=0.1")
    assert bad.returncode == 2 and "only eval.* settings and the lazy policy's" in bad.stderr
