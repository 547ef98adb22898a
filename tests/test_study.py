"""Studies: seeds trained and evaluated together, aggregated with CIs, through the CLI.

One study of two seeds on the smoke preset is run through the CLI once per module;
the tests read its directory.  "Seed i of a study reproduces a single run of seed i
up to the chaos of training" is checked step by step: the dataset, neighbourhoods
and initial state are bitwise those of the single run; one training cycle of the
vmapped seeds stays within a bound far below what a real difference would cause
(see test_one_cycle_matches_the_single_run); evaluation keys are the single run's.
"""

import json
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lazyq_jax.checkpoint import load_checkpoint
from lazyq_jax.config import ConfigError, override, preset
from lazyq_jax.data import load_dataset
from lazyq_jax.pipeline import neighbours_for, prepare_dataset, run_keys
from lazyq_jax.study import (check_methods, check_seeds, method_summary, parse_method,
                             prepare_study_data, seed_config, stacked_neighbours)
from lazyq_jax.train import make_train_for
from lazyq_jax.types import Transitions, pad_transitions

SMOKE = preset("smoke")
SEEDS = [3, 4]


def cli(*args, timeout=900):
    return subprocess.run([sys.executable, "-m", "lazyq_jax", *args], capture_output=True,
                          text=True, timeout=timeout,
                          env={**os.environ, "LAZYQ_COMPILE_CACHE": "off"})


@pytest.fixture(scope="module")
def study_dir(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("study") / "smoke"
    out = cli("study", "--preset", "smoke", "--seeds", "2", "--first-seed", "3", "--methods",
              "lazy,bc", "--run-dir", str(run_dir), "--no-progress")
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-3000:]
    return run_dir


def test_results_schema_summary_and_figure(study_dir):
    results = json.loads((study_dir / "results.json").read_text())
    assert results["seeds"] == SEEDS
    lazy = results["methods"]["lazy"]
    assert [row["seed"] for row in lazy["per_seed"]] == SEEDS
    for row in lazy["per_seed"]:
        assert {"seed", "axis_correct_rate", "overall_correct_rate", "long_horizon_successes",
                "long_horizon_rollouts"} <= set(row)
        assert row["long_horizon_rollouts"] == SMOKE.eval.long_rollouts
        assert len(row["per_direction_correct_rate"]) == SMOKE.eval.n_directions
    for name in ("axis_correct_rate", "overall_correct_rate", "long_horizon_success_rate"):
        s = lazy["summary"][name]
        values = [row[name] for row in lazy["per_seed"]]
        assert s["n"] == 2 and np.isclose(s["mean"], np.mean(values))
        assert 0 <= s["ci95"][0] <= s["mean"] <= s["ci95"][1] <= 1
    assert len(results["datasets"]["positives_by_octant"]["per_seed"]) == 2
    bc = results["methods"]["bc"]  # a baseline: same schema, same seeds
    assert [row["seed"] for row in bc["per_seed"]] == SEEDS and set(bc["summary"]) == set(lazy["summary"])
    steps = json.loads((study_dir / "methods" / "bc" / "config.json").read_text())["config"]["steps"]
    tc = SMOKE.train  # lazy Q's budget: cycles x epochs x minibatches of the smallest dataset
    assert steps == tc.cycles * tc.epochs * (min(row for row in results["datasets"]["rows"]) // tc.batch_size)
    summary = (study_dir / "summary.md").read_text()
    assert "| lazy |" in summary and "| bc |" in summary
    for name in ("per_direction.png", "methods.png"):
        png = study_dir / "figures" / name
        assert png.stat().st_size > 10_000 and png.read_bytes()[:4] == b"\x89PNG"


def test_seeds_are_independent_replicates(study_dir):
    a, b = (load_dataset(study_dir / "seeds" / str(s) / "dataset.npz")[0] for s in SEEDS)
    assert not np.array_equal(np.asarray(a.s[:50]), np.asarray(b.s[:50]))
    state, _ = load_checkpoint(study_dir / "lazy" / "checkpoints", seeds=SEEDS)
    assert int(np.asarray(state.cycle)[0]) == SMOKE.train.cycles
    for leaf in jax.tree.leaves(state.params):
        leaf = np.asarray(leaf)
        assert np.all(np.isfinite(leaf)) and not np.array_equal(leaf[0], leaf[1])
    metrics = [json.loads(line) for line in (study_dir / "lazy" / "metrics.jsonl").read_text().splitlines()]
    assert [m["cycle"] for m in metrics] == [1, 2, 3]
    assert all(len(m["loss"]) == 2 and m["loss"][0] != m["loss"][1] for m in metrics)


def test_datasets_and_neighbourhoods_are_the_single_runs(study_dir, tmp_path):
    sd = prepare_study_data(SMOKE, study_dir, SEEDS, progress=False)  # reuses the study's files
    idx = np.asarray(stacked_neighbours(SMOKE, sd))
    for i, seed in enumerate(SEEDS):
        single = prepare_dataset(seed_config(SMOKE, seed), tmp_path / str(seed), progress=False)
        for a, b in zip(jax.tree.leaves(single), jax.tree.leaves(sd.datasets[i])):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
        n = single.size
        np.testing.assert_array_equal(idx[i, :n], np.asarray(neighbours_for(seed_config(SMOKE, seed), single)))
        assert np.all(idx[i, n:] == 0)  # padding rows


def test_one_cycle_matches_the_single_run(study_dir):
    """The vmapped, padded cycle against each seed's own unpadded, unbatched cycle.

    Both start from bitwise the same state; the batched kernels round differently, and
    training is chaotic: on the smoke data a relative nudge of 1e-7 to the initial
    weights grows to ~1e-3 in the parameters within two epochs.  So the comparison
    runs 15 Adam steps and is calibrated in the same process: the study's difference must
    stay within 10x what that 1e-7 nudge causes in the single run (rounding differences
    are at most of that size), while a wrong row, key or padding in a batch changes the
    parameters by the order of what training moves them (asserted to be far larger).
    """
    cfg = override(SMOKE, ["train.epochs=1", "train.batch_size=1024"])  # 15 Adam steps
    sd = prepare_study_data(cfg, study_dir, SEEDS, progress=False)
    idx = stacked_neighbours(cfg, sd)
    trainer = make_train_for(cfg)
    keys = jnp.stack([run_keys(seed_config(cfg, s))["train"] for s in SEEDS])
    states = jax.vmap(trainer.init)(keys)
    stepped, _ = jax.jit(jax.vmap(trainer.run_cycle))(states, sd.stacked, idx, sd.n_valid)
    one_cycle = jax.jit(trainer.run_cycle)
    params_diff = lambda a, b: max(float(np.abs(np.asarray(x) - np.asarray(y)).max())
                                   for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)))
    for i, seed in enumerate(SEEDS):
        single0 = trainer.init(run_keys(seed_config(cfg, seed))["train"])
        for a, b in zip(jax.tree.leaves(single0), jax.tree.leaves(jax.tree.map(lambda x: x[i], states))):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
        n = sd.datasets[i].size
        single, _ = one_cycle(single0, sd.datasets[i], idx[i, :n])
        nudged, _ = one_cycle(single0.replace(params=jax.tree.map(lambda p: p * (1 + 1e-7),
                                                                  single0.params)),
                              sd.datasets[i], idx[i, :n])
        chaos = params_diff(nudged.params, single.params)
        moved = params_diff(single.params, single0.params)
        diff = params_diff(single.params, jax.tree.map(lambda x: x[i], stepped.params))
        assert 100 * chaos < moved  # the check can fail: a real difference is ~moved
        assert diff <= 10 * chaos, (seed, diff, chaos)


def test_padding_does_not_change_training():
    """A dataset padded with zero rows (n_valid = its size) trains bitwise as unpadded."""
    cfg = SMOKE
    rng = np.random.default_rng(0)
    n = 700
    f = lambda *shape: jnp.asarray(rng.uniform(-1, 1, (n, *shape)), jnp.float32)
    data = Transitions(s=f(2), a=f(2), s_next=f(2), r=jnp.sign(f()), g=f(), done=f() > 0.8)
    idx = jnp.asarray(rng.integers(0, n, (n, 20)), jnp.int32)
    trainer = make_train_for(cfg)
    state = trainer.init(jax.random.PRNGKey(0))
    ref, m_ref = jax.jit(trainer.run_cycle)(state, data, idx)
    padded = pad_transitions(data, n + 333)
    idx_p = jnp.concatenate([idx, jnp.zeros((333, 20), jnp.int32)])
    out, m_out = jax.jit(trainer.run_cycle)(state, padded, idx_p, n)
    for a, b in zip(jax.tree.leaves(ref), jax.tree.leaves(out)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    for name in ("target_mean", "target_std", "clip_fraction", "beta_norm_mean", "loss"):
        np.testing.assert_allclose(m_out[name], m_ref[name], rtol=1e-5)


def test_resume_reuses_everything_and_mismatches_are_refused(study_dir):
    before = (study_dir / "results.json").read_text()
    again = cli("study", "--preset", "smoke", "--seeds", "2", "--first-seed", "3", "--methods",
                "lazy,bc", "--run-dir", str(study_dir), "--resume", "--no-progress")
    assert again.returncode == 0, again.stderr[-3000:]
    log = again.stdout + again.stderr
    assert "lazy: cycle" not in log and "bc: reusing its trained state" in log  # nothing retrained
    assert json.loads((study_dir / "results.json").read_text()) == json.loads(before)
    subset = cli("study", "--preset", "smoke", "--seeds", "2", "--first-seed", "3", "--methods",
                 "bc", "--run-dir", str(study_dir), "--resume", "--no-progress")
    assert subset.returncode == 0, subset.stderr[-3000:]
    assert "results.json keeps lazy" in subset.stdout + subset.stderr  # not dropped
    assert json.loads((study_dir / "results.json").read_text()) == json.loads(before)
    refused = cli("study", "--preset", "smoke", "--seeds", "2", "--first-seed", "3", "--run-dir",
                  str(study_dir), "--no-progress")
    assert refused.returncode == 2 and "--resume" in refused.stderr
    other = cli("study", "--preset", "smoke", "--seeds", "3", "--run-dir", str(study_dir),
                "--resume", "--no-progress")
    assert other.returncode == 2 and "other seeds" in other.stderr
    bad = cli("study", "--preset", "smoke", "--methods", "lazy,sarsa", "--run-dir", str(study_dir))
    assert bad.returncode == 2 and "unknown method" in bad.stderr


def test_argument_checks():
    for seeds in ([], [1, 1], [-1], [0.5]):
        with pytest.raises(ConfigError):
            check_seeds(seeds)
    with pytest.raises(ConfigError, match="unknown method"):
        check_methods(["lazy", "nope"])
    with pytest.raises(ConfigError, match="field=value"):
        check_methods(["iql:temperature"])
    with pytest.raises(ConfigError, match="takes no options"):
        check_methods(["lazy:train.clip=false"])
    with pytest.raises(ConfigError, match="distinct"):
        check_methods(["bc", "bc"])
    assert parse_method("iql:temperature=10:budget=4") == ("iql", {"temperature": "10", "budget": "4"})


def test_summary_of_hand_made_results():
    def result(seed, correct):  # 4 directions x 5 episodes; correct per direction
        per_goal = [{"goal": g, "correct": c, "wrong": 5 - c, "not_pushed": 0}
                    for g, c in zip(np.arange(4) * np.pi / 4, correct)]
        return {"seed": seed, "protocol_a": {"per_goal": per_goal, "axis_correct_rate":
                                             (correct[0] + correct[2]) / 10,
                                             "overall_correct_rate": sum(correct) / 20},
                "protocol_b": {"successes": 9, "rollouts": 10}}

    out = method_summary([result(0, [5, 1, 4, 0]), result(1, [3, 1, 5, 2])])
    rows = out["per_seed"]
    assert rows[0]["diagonal_correct_rate"] == 0.1 and rows[1]["diagonal_correct_rate"] == 0.3
    assert np.isclose(out["summary"]["diagonal_correct_rate"]["mean"], 0.2)
    assert np.isclose(out["summary"]["long_horizon_success_rate"]["mean"], 0.9)
    assert out["summary"]["long_horizon_success_rate"]["ci95"] == [0.9, 0.9]
    np.testing.assert_allclose([d["mean"] for d in out["per_direction"]], [0.8, 0.2, 0.9, 0.2])
