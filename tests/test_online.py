"""Online lazy Q (the runner's online data source) on a tiny config, two seeds in one
program: the rounds, their data, their resume, the reload."""

import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lazyq_jax import tasks
from lazyq_jax.config import ConfigError, override
from lazyq_jax.data import episodes_to_transitions, load_dataset
from lazyq_jax.run import evaluate_run, load_run, run
from lazyq_jax.run.rundir import read_jsonl
from lazyq_jax.run.sources import OnlineRounds, SeedData
from lazyq_jax.types import Transitions, pad_transitions

# The smoke preset (400 random starts, about 790 moves) and two online rounds of at most
# 240 moves each (48 episodes of 5 moves), two cycles per round (so a resume can start inside
# a round).  The budget of 1700 moves pads round 0 to half of it (850 moves' rows) and round 1
# outgrows that: the arrays double once.
TINY = override(tasks.preset("push", "smoke"), [
    "collect.n_starts=400", "train.cycles=2", "online.rounds=2", "online.episodes=48",
    "online.max_steps=5", "online.max_moves=1700", "online.cycles=2", "online.eval_episodes=2",
    "eval.n_directions=8", "eval.episodes_per_direction=2", "eval.long_rollouts=2",
    "eval.long_max_steps=20"])
SEEDS = [0, 1]


def tree_equal(a, b):
    return all(jax.tree.leaves(jax.tree.map(lambda x, y: bool(np.array_equal(x, y)), a, b)))


@pytest.fixture(scope="module")
def online_run(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("online")
    results = run(TINY, run_dir, seeds=SEEDS, progress=False)
    return run_dir, results, load_run(run_dir)


def test_rounds_grow_the_data_within_the_budget_and_compile_once(online_run):
    run_dir, _, loaded = online_run
    rounds = read_jsonl(run_dir / "lazy" / "rounds.jsonl")
    n_goals, o = TINY.collect.n_goals, TINY.online
    assert [r["round"] for r in rounds] == [0, 1, 2] and [r["block"] for r in rounds] == [2, 4, 6]
    sd = loaded.data
    assert sd.capacity == o.max_moves * n_goals
    for i, seed in enumerate(SEEDS):
        moves = [r["seeds"][i]["moves_total"] for r in rounds]
        quota = (o.max_moves - moves[0]) // o.rounds
        added = [r["counts"]["moves_kept"][i] for r in rounds[1:]]
        assert all(0 < a <= quota for a in added) and moves[1:] == [moves[0] + added[0], moves[-1]]
        assert moves[-1] == moves[0] + sum(added) <= o.max_moves
        assert int(sd.n_valid[i]) == moves[-1] * n_goals and not np.asarray(sd.stacked.r[i, int(sd.n_valid[i]):]).any()
        for r in rounds[1:]:
            c = {k: v[i] for k, v in r["counts"].items()}
            assert c["episodes"] == o.episodes and c["moves_simulated"] <= o.episodes * o.max_steps
            assert c["moves_kept"] <= c["moves_simulated"] and c["correct"] <= c["pushed"]
            part, meta = load_dataset(run_dir / "data" / str(seed) / f"round_{r['round']}.npz")
            assert meta == {"seed": seed, "round": r["round"]} and part.size == c["moves_kept"] * n_goals
    # The seeds' data grew differently (each with its own policy).
    assert rounds[-1]["seeds"][0]["moves_total"] != rounds[-1]["seeds"][1]["moves_total"] or not tree_equal(
        sd.seed_data(0), sd.seed_data(1))
    # The arrays doubled once (round 1 outgrew half the budget): the rollout and the training
    # block each compiled once per size.
    assert rounds[0]["seeds"][0]["moves_total"] <= o.max_moves // 2 < rounds[1]["seeds"][0]["moves_total"]
    assert rounds[-1]["compiled"] == {"run_block": 2, "explore": 2}


def test_collected_moves_are_valid_relabelled_transitions(online_run):
    _, _, loaded = online_run
    push, n_goals, o = TINY.collect.push, TINY.collect.n_goals, TINY.online
    eps = jax.device_get(tasks.get("push").explore(loaded.policy(), jax.random.PRNGKey(7), TINY))
    counts = eps.pop("counts")
    moved = eps["moved"].astype(bool)
    # Moves have the action length; fingers start behind the disk for their episode's goal.
    np.testing.assert_allclose(np.linalg.norm(eps["a"], axis=-1), push.action_length, rtol=1e-5)
    toward = np.stack([np.cos(eps["goal"]), np.sin(eps["goal"])], -1)
    assert np.all(np.einsum("bi,bi->b", eps["s"][:, 0], toward) < 0)
    # An episode's states chain: the next move starts where the last one ended.
    np.testing.assert_array_equal(eps["s"][:, 1:], eps["s_next"][:, :-1])
    # Eq. (15) recomputed in NumPy from the relative states: s' - s = a - delta_disk.
    delta = np.asarray(eps["a"] - (eps["s_next"] - eps["s"]), np.float64)
    dist = np.linalg.norm(delta, axis=-1)
    labels = np.asarray(eps["g"], np.float64)
    cos = (delta[..., None, 0] * np.cos(labels) + delta[..., None, 1] * np.sin(labels)) / np.maximum(
        dist[..., None], 1e-12)
    expect = np.where(dist[..., None] >= push.move_threshold,
                      np.where(cos > push.cos_threshold, 1.0, -1.0), 0.0)
    # (float32 states against float64: compare away from the two thresholds)
    clear = ((np.abs(dist - push.move_threshold) > 1e-4)[..., None]
             & (np.abs(cos - push.cos_threshold) > 1e-3))
    assert clear.mean() > 0.95
    live = np.cumsum(moved, axis=1) - moved == 0  # moves of an episode up to its first push
    np.testing.assert_array_equal(np.asarray(eps["r"])[clear & live[..., None]],
                                  expect[clear & live[..., None]])
    np.testing.assert_array_equal(moved, np.asarray(eps["r"])[..., 0] != 0)
    assert int(counts["pushed"]) == int(moved.any(1).sum())
    # The relabelled transitions: every move up to and including an episode's first push.
    new = episodes_to_transitions(eps, n_goals)
    first = np.where(moved.any(1), moved.argmax(1) + 1, o.max_steps)
    assert new.size == first.sum() * n_goals
    assert int(np.asarray(new.done).sum()) == moved.any(1).sum() * n_goals
    r, done = np.asarray(new.r), np.asarray(new.done)
    np.testing.assert_array_equal(r != 0, done)
    lo, _, hi, _ = tasks.get("push").search_bounds(TINY)
    assert np.all((np.asarray(new.s) > lo) & (np.asarray(new.s) < hi))
    assert moved.any() and (r > 0).any()


def test_resume_equals_the_uninterrupted_run(online_run, tmp_path):
    """Stopped inside round 2 (its data collected, one of its two cycles trained) and at the
    end of round 1 (round 2 not collected yet): the resumed run (the same programs) ends
    with bitwise the same data and parameters."""
    run_dir, _, loaded = online_run
    for keep, drop_round_2 in ((5, False), (4, True)):
        copy = tmp_path / f"resume_{keep}"
        shutil.copytree(run_dir, copy)
        for block in range(keep + 1, 7):
            shutil.rmtree(copy / "lazy" / "checkpoints" / str(block))
        if drop_round_2:
            for seed in SEEDS:
                (copy / "data" / str(seed) / "round_2.npz").unlink()
        run(TINY, copy, seeds=SEEDS, resume=True, progress=False)
        resumed = load_run(copy)
        assert tree_equal(resumed.states, loaded.states)
        assert tree_equal(resumed.data.stacked, loaded.data.stacked)
        np.testing.assert_array_equal(resumed.data.n_valid, loaded.data.n_valid)
        assert [r["round"] for r in read_jsonl(copy / "lazy" / "rounds.jsonl")] == [0, 1, 2]


def test_evaluation_reloads_the_online_data(online_run):
    run_dir, results, _ = online_run
    again = evaluate_run(run_dir, figures=True, progress=False)
    assert again["methods"]["lazy"]["per_seed"] == results["methods"]["lazy"]["per_seed"]
    assert (run_dir / "figures" / "lazy" / "online_curve.png").stat().st_size > 10_000


def test_the_rounds_budget_counts_in_moves():
    rounds = OnlineRounds(tasks.get("push"), TINY, None)
    assert rounds.total_blocks() == 6 and [rounds.round_end(r) for r in range(3)] == [2, 4, 6]
    assert [rounds.round_starting(b) for b in range(7)] == [None, None, 1, None, 2, None, None]
    assert [rounds.rounds_with_data(b) for b in range(7)] == [0, 0, 0, 1, 1, 2, 2]
    assert rounds.quota(500) == 600


@pytest.mark.parametrize("assignment, message", [
    ("online.epsilon=1.5", "epsilon"), ("online.action_noise=-0.1", "action_noise"),
    ("collect.explore_start=front", "'behind' or 'anywhere'"), ("online.rounds=-1", "rounds"),
    ("collect.explore_range=0.2", "contact"),
])
def test_bad_online_settings_are_refused_with_the_reason(assignment, message):
    with pytest.raises(ConfigError, match=message):
        override(TINY, [assignment])


def test_online_runs_refuse_offline_baselines_and_small_budgets(tmp_path):
    with pytest.raises(ConfigError, match="run them offline"):
        run(TINY, tmp_path / "a", methods=["lazy", "bc"])
    with pytest.raises(ConfigError, match="online.max_moves=500 leaves no moves"):
        run(override(TINY, ["online.max_moves=500"]), tmp_path / "b", progress=False)


def test_padding_starts_small_and_doubles_as_the_rounds_grow(tmp_path):
    """The online arrays: the run's capacity halved while the half holds the rows and a
    batch; a round that outgrows them doubles them (valid rows kept, the rest zero)."""
    config = override(TINY, ["online.max_moves=4000", "train.batch_size=64"])
    online = OnlineRounds(tasks.get("push"), config, tmp_path)
    cap, per_move = online.capacity, online.per_move
    assert cap == 4000 * per_move
    for rows in (1, 64, cap // 8, cap // 8 + 1, cap // 4 + 1, cap):
        size = online.size_for(rows)
        # the smallest capacity / 2^j holding max(rows, batch)
        expect = min(cap >> j for j in range(20) if (cap >> j) << j == cap and cap >> j >= max(rows, 64))
        assert size == expect and size >= rows
    rng = np.random.default_rng(0)

    def rows(moves):
        n = moves * per_move
        f = lambda *shape: jnp.asarray(rng.normal(size=(n, *shape)), jnp.float32)
        return Transitions(s=f(2), a=f(2), s_next=f(2), r=f(), g=f(), done=jnp.asarray(rng.random(n) < 0.1))

    base = [rows(300), rows(250)]
    stacked = jax.tree.map(lambda *x: jnp.stack(x), base[0], pad_transitions(base[1], base[0].size))
    sd = SeedData((0, 1), stacked, np.array([300 * per_move, 250 * per_move], np.int32), [{}, {}])
    sd = online.padded(sd)
    assert sd.capacity == online.size_for(300 * per_move) == cap // 8
    extra = [rows(400), rows(100)]
    grown = online.append(sd, extra)
    assert grown.capacity == cap // 4 and list(grown.n_valid) == [700 * per_move, 350 * per_move]
    for i in range(2):
        whole = jax.tree.map(lambda a, b: np.concatenate([a, b]), base[i], extra[i])
        assert tree_equal(grown.seed_data(i), whole)
        assert not np.asarray(grown.stacked.s[i, int(grown.n_valid[i]):]).any()
