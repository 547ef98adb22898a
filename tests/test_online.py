"""Online lazy Q (lazyq_jax.online) on a tiny config: the loop, its data, its resume."""

import json
import shutil

import jax
import numpy as np
import pytest

from lazyq_jax.config import ConfigError, override, preset
from lazyq_jax.data import episodes_to_transitions
from lazyq_jax.evaluate import evaluate_run
from lazyq_jax.online import (capacity_rows, evaluate_online, fit_online, load_online_data,
                              online_bounds, online_policy, read_rounds)

# The smoke preset (400 random starts, about 790 moves) and two online rounds of at most
# 150 moves each, two cycles per round (so a resume can start inside a round).
TINY = override(preset("smoke"), [
    "collect.n_starts=400", "train.cycles=2", "online.rounds=2", "online.episodes=48",
    "online.max_steps=5", "online.max_moves=1100", "online.cycles=2", "online.eval_episodes=2",
    "eval.n_directions=8", "eval.episodes_per_direction=2", "eval.long_rollouts=2",
    "eval.long_max_steps=20"])


def tree_equal(a, b):
    return all(jax.tree.leaves(jax.tree.map(lambda x, y: bool(np.array_equal(x, y)), a, b)))


@pytest.fixture(scope="module")
def online_run(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("online")
    state, data, n_valid, fns = fit_online(TINY, run_dir, progress=False)
    return run_dir, state, data, n_valid, fns


def test_rounds_grow_the_data_within_the_budget_and_compile_once(online_run):
    run_dir, state, data, n_valid, fns = online_run
    rounds = read_rounds(run_dir)
    n_goals, o = TINY.collect.n_goals, TINY.online
    assert [r["round"] for r in rounds] == [0, 1, 2]
    assert [r["cycle"] for r in rounds] == [2, 4, 6] and int(state.cycle) == 6
    moves = [r["moves_total"] for r in rounds]
    quota = (o.max_moves - moves[0]) // o.rounds
    assert all(0 < r["moves_added"] <= quota for r in rounds[1:])
    assert moves[1:] == [moves[0] + rounds[1]["moves_added"], moves[-1]]
    assert moves[-1] <= o.max_moves and n_valid == moves[-1] * n_goals
    assert data.size == capacity_rows(TINY) and not np.asarray(data.r[n_valid:]).any()
    for r in rounds[1:]:
        ep = r["episodes"]
        assert ep["episodes"] == o.episodes and ep["moves_kept"] == r["moves_added"]
        assert ep["moves_simulated"] <= o.episodes * o.max_steps
        assert 0 < r["pushes_added"] <= ep["pushed"]
        positives = sum(octant["positive"] for octant in r["reward_by_goal_octant"])
        assert 0 < positives <= r["pushes_added"] * n_goals
    # The rollout and the training cycle each compiled once for the whole run.
    assert rounds[-1]["compiled"]["rollout"] == 1
    assert rounds[-1]["compiled"]["run_cycle"] == 1
    # The files hold exactly the data the loop trained on.
    files, rows = load_online_data(TINY, run_dir, 2)
    assert rows == [r["rows"] for r in rounds]
    assert tree_equal(files, jax.tree.map(lambda x: x[:n_valid], data))


def test_collected_moves_are_valid_relabelled_transitions(online_run):
    _, state, data, n_valid, fns = online_run
    push, n_goals, o = TINY.collect.push, TINY.collect.n_goals, TINY.online
    policy = online_policy(TINY, fns, state, data, n_valid, TINY.eval.max_level)
    eps = jax.device_get(fns.rollout(policy, jax.random.PRNGKey(7)))
    delta, moved, goal = (np.asarray(eps[k], np.float64) for k in ("delta", "moved", "goal"))
    moved = moved.astype(bool)
    # Moves have the action length; fingers start behind the disk for their goal.
    np.testing.assert_allclose(np.linalg.norm(eps["a"], axis=-1), push.action_length, rtol=1e-5)
    toward = np.stack([np.cos(goal), np.sin(goal)], -1)
    assert np.all(np.einsum("bi,bi->b", eps["s"][:, 0], toward) < 0)
    # An episode's states chain: the next move starts where the last one ended.
    np.testing.assert_array_equal(eps["s"][:, 1:], eps["s_next"][:, :-1])
    # Eq. (15) recomputed in NumPy from the recorded disk displacements.
    dist = np.linalg.norm(delta, axis=-1)
    labels = np.asarray(eps["g"], np.float64)
    cos = (delta[..., None, 0] * np.cos(labels) + delta[..., None, 1] * np.sin(labels)) / np.maximum(
        dist[..., None], 1e-12)
    expect = np.where(dist[..., None] >= push.move_threshold,
                      np.where(cos > push.cos_threshold, 1.0, -1.0), 0.0)
    # (float32 against float64: compare away from the two thresholds)
    clear = ((np.abs(dist - push.move_threshold) > 1e-6)[..., None]
             & (np.abs(cos - push.cos_threshold) > 1e-5))
    assert clear.mean() > 0.99
    np.testing.assert_array_equal(np.asarray(eps["r"])[clear], expect[clear])
    np.testing.assert_array_equal(moved, np.asarray(eps["r"])[..., 0] != 0)
    # The relabelled transitions: every move up to and including an episode's first push.
    new = episodes_to_transitions(eps, n_goals)
    first = np.where(moved.any(1), moved.argmax(1) + 1, o.max_steps)
    assert new.size == first.sum() * n_goals
    assert int(np.asarray(new.done).sum()) == moved.any(1).sum() * n_goals
    r, done = np.asarray(new.r), np.asarray(new.done)
    np.testing.assert_array_equal(r != 0, done)
    lo, _, hi, _ = online_bounds(TINY)
    assert np.all((np.asarray(new.s) > lo) & (np.asarray(new.s) < hi))
    assert moved.any() and (r > 0).any()


def test_resume_equals_the_uninterrupted_run(online_run, tmp_path):
    run_dir, state, data, n_valid, _ = online_run
    # Inside round 2 (its data collected, one of its two cycles trained) and at the end of
    # round 1 (round 2 not collected yet): resuming gives the same data and parameters.
    for keep_cycles, drop_round_2 in ((5, False), (4, True)):
        copy = tmp_path / f"resume_{keep_cycles}"
        shutil.copytree(run_dir, copy)
        for c in range(keep_cycles + 1, 7):
            shutil.rmtree(copy / "checkpoints" / str(c))
        if drop_round_2:
            (copy / "online" / "round_2.npz").unlink()
        resumed, data2, n2, _ = fit_online(TINY, copy, resume=True, progress=False)
        assert int(resumed.cycle) == 6 and n2 == n_valid
        assert tree_equal(resumed.params, state.params)
        assert tree_equal(data2, data)
        assert [r["round"] for r in read_rounds(copy)] == [0, 1, 2]


def test_final_evaluation_and_the_cli_reload(online_run):
    run_dir, state, data, n_valid, fns = online_run
    results = evaluate_online(TINY, run_dir, state, data, n_valid, fns, figures=True)
    assert results["moves"] == n_valid // TINY.collect.n_goals
    assert len(results["protocol_a"]["per_goal"]) == 8
    assert (run_dir / "figures" / "online_curve.png").stat().st_size > 0
    # `evaluate` reloads the online data (not only round 0's): the same results.
    evaluate_run(run_dir, figures=False)
    again = json.loads((run_dir / "eval" / "results.json").read_text())
    assert again["protocol_a"] == results["protocol_a"]
    assert again["protocol_b"] == results["protocol_b"]


@pytest.mark.parametrize("assignment, message", [
    ("online.epsilon=1.5", "epsilon"), ("online.angle_noise=-0.1", "angle_noise"),
    ("online.start=front", "'behind' or 'anywhere'"), ("online.rounds=-1", "rounds"),
    ("online.start_range=0.2", "contact"), ("online.max_moves=500", "max_moves"),
])
def test_bad_online_settings_are_refused_with_the_reason(assignment, message):
    with pytest.raises(ConfigError, match=message):
        override(TINY, [assignment])


def test_an_online_study_refuses_offline_baselines(tmp_path):
    from lazyq_jax.study import run_study

    with pytest.raises(ConfigError, match="offline study"):
        run_study(TINY, tmp_path, seeds=[0], methods=["lazy", "bc"])

