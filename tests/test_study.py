"""Studies through the CLI: every agent on the push task, two seeds trained and evaluated
together, aggregated with CIs; resume; and what a study's seed shares with its single run.

One study (every method, seeds 3 and 4, tiny settings) runs once per module.  A study's
seed is an independent replicate of a single run; what is deterministic is checked
exactly (its dataset, neighbourhoods, initial state and the minibatches it draws,
bitwise), what rounds differently in the batched program within a bound derived from
the magnitudes (the values it bootstraps from); training outcomes of the batched and
the single program are never compared (training is chaotic).
"""

import json

import conftest
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import cli

from lazyq_jax import agents, tasks
from lazyq_jax.config import ConfigError, override
from lazyq_jax.keys import purpose_key
from lazyq_jax.run import load_policy, load_run, run
from lazyq_jax.run.results import method_summary
from lazyq_jax.run.rundir import check_methods, check_seeds, parse_method
from lazyq_jax.run.sources import static_data
from lazyq_jax.targets import bootstrap_table
from lazyq_jax.train import shuffle
from lazyq_jax.types import Transitions, pad_transitions

SEEDS = [3, 4]
METHODS = "lazy,iql,td3bc,dqn,naf,bc,random,scripted"
# Tiny but real: every phase of every method runs, in seconds.
TINY = ["collect.n_starts=150", "collect.n_goals=8", "train.cycles=2", "train.epochs=1",
        "train.batch_size=64", "train.width=16", "eval.episodes_per_direction=2", "eval.max_steps=10",
        "eval.long_rollouts=2", "eval.long_max_steps=10"]
CONFIG = override(tasks.preset("push", "smoke"), TINY)



def sets(assignments):
    return [x for a in assignments for x in ("--set", a)]


@pytest.fixture(scope="module")
def study_dir(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("study") / "push"
    out = cli("study", "--preset", "smoke", "--seeds", "2", "--first-seed", "3", "--methods",
              METHODS, "--run-dir", str(run_dir), "--no-progress", *sets(TINY))
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-3000:]
    return run_dir


def test_results_schema_summary_and_figures(study_dir):
    results = json.loads((study_dir / "results.json").read_text())
    assert results["seeds"] == SEEDS and results["task"] == "push"
    assert list(results["methods"]) == METHODS.split(",")
    lazy = results["methods"]["lazy"]
    assert [row["seed"] for row in lazy["per_seed"]] == SEEDS
    for row in lazy["per_seed"]:
        assert {"seed", "axis_correct_rate", "overall_correct_rate", "long_horizon_successes",
                "long_horizon_rollouts"} <= set(row)
        assert row["long_horizon_rollouts"] == CONFIG.eval.long_rollouts
        assert len(row["per_direction_correct_rate"]) == CONFIG.eval.n_directions
    for name in ("axis_correct_rate", "overall_correct_rate", "long_horizon_success_rate"):
        s = lazy["summary"][name]
        values = [row[name] for row in lazy["per_seed"]]
        assert s["n"] == 2 and np.isclose(s["mean"], np.mean(values))
        assert 0 <= s["ci95"][0] <= s["mean"] <= s["ci95"][1] <= 1
    assert len(results["data"]["positives_by_octant"]["per_seed"]) == 2
    for name, method in results["methods"].items():  # every method: same schema, same seeds
        assert [row["seed"] for row in method["per_seed"]] == SEEDS
        assert set(method["summary"]) == set(lazy["summary"]), name
        gif = study_dir / "figures" / name / "rollouts.gif"
        assert gif.read_bytes()[:6] == b"GIF89a", name
    steps = json.loads((study_dir / "bc" / "method.json").read_text())["config"]["steps"]
    tc = CONFIG.train  # lazy Q's budget: cycles x epochs x minibatches of the smallest dataset
    assert steps == tc.cycles * tc.epochs * (min(results["data"]["rows"]) // tc.batch_size)
    assert results["methods"]["scripted"]["summary"]["axis_correct_rate"]["mean"] >= 0.75
    summary = (study_dir / "summary.md").read_text()
    assert all(f"| {m} |" in summary for m in METHODS.split(","))
    for name in ("per_direction.png", "methods.png"):
        png = study_dir / "figures" / name
        assert png.stat().st_size > 10_000 and png.read_bytes()[:4] == b"\x89PNG"


def test_seeds_are_independent_replicates(study_dir):
    loaded = load_run(study_dir)
    a, b = (loaded.data.seed_data(i) for i in (0, 1))
    assert not np.array_equal(np.asarray(a.s[:50]), np.asarray(b.s[:50]))
    for leaf in jax.tree.leaves(loaded.states.params):
        leaf = np.asarray(leaf)
        assert np.all(np.isfinite(leaf)) and not np.array_equal(leaf[0], leaf[1])
    metrics = [json.loads(line) for line in (study_dir / "lazy" / "metrics.jsonl").read_text().splitlines()]
    assert [m["block"] for m in metrics] == [1, 2]
    assert all(len(m["loss"]) == 2 and m["loss"][0] != m["loss"][1] for m in metrics)


def test_what_a_seed_shares_with_its_single_run(study_dir, tmp_path):
    """Seed 4 of the study against ``train --set seed=4``'s inputs, computed alone."""
    loaded = load_run(study_dir)
    task, agent, sd = loaded.task, loaded.agent, loaded.data
    i, seed = 1, SEEDS[1]
    single = static_data(task, override(CONFIG, [f"seed={seed}"]), tmp_path, [seed], progress=False)
    data = single.seed_data(0)
    # the dataset: bitwise (the same collection program per seed)
    for x, y in zip(jax.tree.leaves(data), jax.tree.leaves(sd.seed_data(i))):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    # the neighbourhoods: bitwise, from the padded stack and from the data alone
    n = data.size
    padded = jax.tree.map(lambda x: x[i], sd.stacked)
    nb_study = agent.prepare(seed, padded, int(sd.n_valid[i]), 0)
    nb_single = agent.prepare(seed, data, n, 0)
    np.testing.assert_array_equal(np.asarray(nb_study.idx[:n]), np.asarray(nb_single.idx))
    assert np.all(np.asarray(nb_study.idx[n:]) == 0)
    # the initial state: bitwise (vmapped init against one)
    key = purpose_key(seed, "train")
    keys = jnp.stack([purpose_key(s, "train") for s in SEEDS])
    stacked0 = jax.vmap(agent.init)(keys, sd.stacked)
    one0 = agent.init(key, data)
    for x, y in zip(jax.tree.leaves(one0), jax.tree.leaves(jax.tree.map(lambda x: x[i], stacked0))):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    # the minibatches an epoch draws: bitwise (a padded dataset shuffles its rows as unpadded)
    k = jax.random.PRNGKey(7)
    perm_stacked = jax.vmap(lambda nv: shuffle(k, sd.capacity, nv))(jnp.asarray(sd.n_valid))
    np.testing.assert_array_equal(np.asarray(perm_stacked[i, :n]), np.asarray(shuffle(k, n, n)))
    # the values the first targets bootstrap from, y = r + gamma V(s', g): the batched
    # program rounds differently; float32 rounding of the 9-layer network is at most about
    # depth x width x 2^-24 relative (9 x 16 x 6e-8 = 9e-6): 1e-4 of the largest |y| is
    # 10x that, while a wrong row or padding changes y by the order of y itself.
    gamma = CONFIG.train.gamma
    batched = jax.jit(jax.vmap(lambda st, d: bootstrap_table(agent.value_fn(st), d, gamma)))(
        stacked0, sd.stacked)[i, :n]
    alone = jax.jit(lambda st, d: bootstrap_table(agent.value_fn(st), d, gamma))(one0, data)
    scale = float(np.max(np.abs(np.asarray(alone))))
    np.testing.assert_allclose(np.asarray(batched), np.asarray(alone), atol=1e-4 * scale, rtol=0)


def test_padding_does_not_change_training():
    """A dataset padded with zero rows (n_valid = its size) trains bitwise as unpadded (the
    same program: only the padding differs, which is never read)."""
    rng = np.random.default_rng(0)
    n = 700
    f = lambda *shape: jnp.asarray(rng.uniform(-1, 1, (n, *shape)), jnp.float32)
    data = Transitions(s=f(2), a=f(2), s_next=f(2), r=jnp.sign(f()), g=f(), done=f() > 0.8)
    idx = jnp.asarray(rng.integers(0, n, (n, 20)), jnp.int32)
    trainer = agents.make("lazy", agents.LazyConfig(train=CONFIG.train)).trainer
    state = trainer.init(jax.random.PRNGKey(0), data)
    padded = pad_transitions(data, n + 333)
    idx_p = jnp.concatenate([idx, jnp.zeros((333, 20), jnp.int32)])
    run_cycle = jax.jit(trainer.run_cycle)
    ref, m_ref = run_cycle(state, data, idx, n)
    out, m_out = jax.jit(trainer.run_cycle)(state, padded, idx_p, n)
    for a, b in zip(jax.tree.leaves(ref), jax.tree.leaves(out)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    for name in ("target_mean", "target_std", "clip_fraction", "beta_norm_mean", "loss"):
        np.testing.assert_allclose(m_out[name], m_ref[name], rtol=1e-5)


def test_policies_reload_for_user_code(study_dir):
    s = jnp.asarray([[-0.4, 0.0], [0.0, -0.4], [0.5, 0.5]], jnp.float32)
    g = jnp.asarray([0.0, np.pi / 2, 1.0], jnp.float32)
    for method in ("lazy", "td3bc", "dqn", "scripted"):
        for seed in SEEDS:
            act = load_policy(study_dir, method, seed)
            a = np.asarray(act(jax.random.PRNGKey(0), s, g))
            assert a.shape == (3, 2) and np.all(np.isfinite(a))
            assert np.all((np.abs(np.linalg.norm(a, axis=1) - 0.1) < 1e-5) | (np.abs(a).sum(1) == 0))


def test_resume_reuses_everything_and_mismatches_are_refused(study_dir):
    before = (study_dir / "results.json").read_text()
    stamp = (study_dir / "lazy" / "checkpoints" / "2").stat().st_mtime_ns
    again = cli("study", "--preset", "smoke", "--seeds", "2", "--first-seed", "3", "--methods",
                "lazy,bc", "--run-dir", str(study_dir), "--resume", "--no-progress", *sets(TINY))
    assert again.returncode == 0, again.stderr[-3000:]
    log = again.stdout + again.stderr
    assert ": block" not in log  # nothing retrained
    assert (study_dir / "lazy" / "checkpoints" / "2").stat().st_mtime_ns == stamp
    results = json.loads((study_dir / "results.json").read_text())
    assert results == json.loads(before)  # re-evaluation reused; the other methods' rows kept
    refused = cli("study", "--preset", "smoke", "--seeds", "2", "--first-seed", "3", "--run-dir",
                  str(study_dir), "--no-progress", *sets(TINY))
    assert refused.returncode == 2 and "--resume" in refused.stderr
    other = cli("study", "--preset", "smoke", "--seeds", "3", "--run-dir", str(study_dir),
                "--resume", "--no-progress", *sets(TINY))
    assert other.returncode == 2 and "holds a run of seeds [3, 4], not [0, 1, 2]" in other.stderr
    settings = cli("study", "--preset", "smoke", "--seeds", "2", "--first-seed", "3", "--run-dir",
                   str(study_dir), "--resume", "--no-progress", *sets(TINY + ["collect.n_goals=9"]))
    assert settings.returncode == 2 and "collect.n_goals" in settings.stderr
    arm = cli("study", "--task", "arm", "--preset", "smoke", "--seeds", "2", "--first-seed", "3",
              "--run-dir", str(study_dir), "--resume", "--no-progress")
    assert arm.returncode == 2 and "task 'push', not 'arm'" in arm.stderr
    # a baseline's budget follows lazy Q's cycles: more cycles on resume change it, refused
    budget = cli("study", "--preset", "smoke", "--seeds", "2", "--first-seed", "3", "--methods", "bc",
                 "--run-dir", str(study_dir), "--resume", "--no-progress",
                 *sets(TINY + ["train.cycles=3"]))
    assert budget.returncode == 2 and "bc trained with other settings (config.steps)" in budget.stderr
    assert (study_dir / "results.json").read_text() == before  # nothing was touched


def test_names_are_checked_and_listed():
    bad = cli("study", "--preset", "smoke", "--methods", "lazy,sarsa", "--run-dir", "unused")
    assert bad.returncode == 2 and "unknown method 'sarsa'" in bad.stderr
    assert "lazy, iql, td3bc, dqn, naf, bc, gcivl, gciql, gcbc, qrl, crl, hiql, random, scripted" in bad.stderr
    task = cli("train", "--task", "crane")
    assert task.returncode == 2 and "unknown task 'crane'; known tasks: push, arm, arm-long" in task.stderr
    preset = cli("train", "--task", "arm", "--preset", "forgiving")
    assert preset.returncode == 2 and "its presets: paper, online, online4x, static4x, smoke" in preset.stderr
    field = cli("train", "--set", "train.widht=3")
    assert field.returncode == 2 and "unknown config field 'train.widht'" in field.stderr
    for seeds in ([], [1, 1], [-1], [0.5]):
        with pytest.raises(ConfigError):
            check_seeds(seeds)
    with pytest.raises(ConfigError, match="field=value"):
        check_methods(["iql:temperature"])
    with pytest.raises(ConfigError, match="takes no options"):
        check_methods(["lazy:train.clip=false"])
    with pytest.raises(ConfigError, match="distinct"):
        check_methods(["bc", "bc"])
    spec = parse_method("iql:temperature=10:budget=4")
    assert spec.name == "iql" and dict(spec.options) == {"temperature": "10", "budget": "4"}


def test_summary_of_hand_made_results():
    def result(seed, correct):  # 4 directions x 5 episodes; correct per direction
        per_goal = [{"goal": g, "correct": c, "wrong": 5 - c, "not_pushed": 0}
                    for g, c in zip(np.arange(4) * np.pi / 4, correct)]
        return {"seed": seed, "protocol_a": {"per_goal": per_goal},
                "protocol_b": {"successes": 9, "rollouts": 10}}

    out = method_summary(tasks.get("push"), [result(0, [5, 1, 4, 0]), result(1, [3, 1, 5, 2])])
    rows = out["per_seed"]
    assert rows[0]["diagonal_correct_rate"] == 0.1 and rows[1]["diagonal_correct_rate"] == 0.3
    assert rows[0]["axis_correct_rate"] == 0.9 and rows[1]["overall_correct_rate"] == 0.55
    assert np.isclose(out["summary"]["diagonal_correct_rate"]["mean"], 0.2)
    assert np.isclose(out["summary"]["long_horizon_success_rate"]["mean"], 0.9)
    assert out["summary"]["long_horizon_success_rate"]["ci95"] == [0.9, 0.9]
    np.testing.assert_allclose([d["mean"] for d in out["per_direction"]], [0.8, 0.2, 0.9, 0.2])


def test_the_suites_timeout_scale_is_validated(monkeypatch):
    """``LAZYQ_TEST_TIMEOUT_SCALE`` multiplies the suite's subprocess limits; anything but a
    positive finite number is refused with what to set."""
    monkeypatch.setenv("LAZYQ_TEST_TIMEOUT_SCALE", "2.5")
    assert conftest._timeout_scale() == 2.5
    for bad in ("0", "-1", "nan", "inf", "slow"):
        monkeypatch.setenv("LAZYQ_TEST_TIMEOUT_SCALE", bad)
        with pytest.raises(pytest.UsageError, match="must be a positive number"):
            conftest._timeout_scale()


def test_a_method_that_cannot_learn_from_the_data_is_refused_before_any_trains(tmp_path):
    """QRL's goals must be states and the push's are angles: the run stops with a config error
    before lazy Q, listed first, trains."""
    with pytest.raises(ConfigError, match="goals must be states"):
        run(CONFIG, tmp_path / "r", seeds=[3], methods=["lazy", "qrl"], progress=False)
    assert (tmp_path / "r" / "data").exists() and not (tmp_path / "r" / "lazy").exists()
