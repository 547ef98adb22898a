"""Every agent on an arm task through the CLI (joint space: d_s = 3 and 5, n_a = 3), the
run directory reloaded (evaluate, plot, load_policy), and the static source's resume.

One study per arm task (one seed, tiny settings) runs once per module: lazy Q, TD3+BC (which
the reload and resume tests use on both) and the two reference policies on both tasks, each
other baseline on one of them, so that every agent meets joint space in half the time of
running all of them twice.
"""

import json
import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import cli

from lazyq_jax import agents, tasks
from lazyq_jax.checkpoint import CheckpointError, load_checkpoint
from lazyq_jax.config import override
from lazyq_jax.run import load_policy, load_run, run
from lazyq_jax.run.sources import static_data

METHODS = {"arm": "lazy,iql,td3bc,naf,random,scripted", "arm-long": "lazy,td3bc,dqn,bc,random,scripted"}
TINY = ["collect.n_starts=120", "collect.n_goals=6", "train.cycles=2", "train.epochs=1",
        "train.batch_size=64", "train.width=16", "eval.episodes_per_direction=2", "eval.max_steps=6",
        "eval.long_rollouts=2", "eval.long_max_steps=6", "neighbours.k=10"]
# arm-long's lazy Q measures its neighbourhoods in the fingertip's space and fits the state
# offsets too (the arms' defaults, through the CLI, the resume and the reloads); arm's in
# joint space with plain Eq. (4) models (the paper's), so that both kinds are run.
LONG = ["neighbours.features=fingertip", "neighbours.radius_s=0.08", "neighbours.local_model=action+state"]
JOINT = ["neighbours.features=state", "neighbours.radius_s=0.12", "neighbours.local_model=action"]
EXTRA = {"arm": JOINT, "arm-long": LONG}



def sets(assignments):
    return [x for a in assignments for x in ("--set", a)]


@pytest.fixture(scope="module")
def studies(tmp_path_factory):
    root = tmp_path_factory.mktemp("arms")
    for task in ("arm", "arm-long"):
        out = cli("study", "--task", task, "--preset", "smoke", "--seeds", "1", "--methods", METHODS[task],
                  "--run-dir", str(root / task), "--no-progress", *sets(TINY + EXTRA[task]))
        assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-3000:]
    return root


def test_the_studies_cover_every_agent():
    """A new agent must be added to one of the studies (the goal-conditioned ones run on
    pointmaze, tests/test_pointmaze.py)."""
    covered = {m for methods in METHODS.values() for m in methods.split(",")}
    assert covered == set(agents.METHODS) - {"gcivl", "gciql", "gcbc", "qrl", "crl", "hiql"}


@pytest.mark.parametrize("task", ["arm", "arm-long"])
def test_every_method_ran_on_the_arm(studies, task):
    results = json.loads((studies / task / "results.json").read_text())
    assert results["task"] == task and list(results["methods"]) == METHODS[task].split(",")
    for name, method in results["methods"].items():
        row = method["per_seed"][0]
        assert 0 <= row["axis_correct_rate"] <= 1
        assert ("long_horizon_success_rate" in row) == (task == "arm-long")
        assert (studies / task / "figures" / name / "rollouts.gif").read_bytes()[:6] == b"GIF89a"
        assert (studies / task / "figures" / name / "arm_trajectories.png").stat().st_size > 10_000
    assert (studies / task / "figures" / "lazy" / "arm_value.png").exists()
    assert (studies / task / "figures" / "methods.png").exists()


@pytest.mark.parametrize("task, d_s", [("arm", 3), ("arm-long", 5)])
def test_policies_reload_for_user_code(studies, task, d_s):
    loaded = load_run(studies / task)
    data = loaded.data.seed_data(0)
    assert data.s.shape[1] == d_s and data.a.shape[1] == 3
    s, g = data.s[:5], data.g[:5]
    for method in METHODS[task].split(","):
        a = np.asarray(load_policy(studies / task, method)(jax.random.PRNGKey(0), s, g))
        assert a.shape == (5, 3) and np.all(np.isfinite(a))
        norm = np.linalg.norm(a, axis=1)
        assert np.all((np.abs(norm - 0.12) < 1e-5) | (norm == 0)), (method, norm)
    lazy = np.asarray(load_policy(studies / task)(jax.random.PRNGKey(0), s, g))
    assert np.all(np.linalg.norm(lazy, axis=1) > 0)  # data points have neighbourhoods


def test_evaluate_and_plot_reload_any_run(studies):
    before = json.loads((studies / "arm" / "results.json").read_text())
    gif = studies / "arm" / "figures" / "td3bc" / "rollouts.gif"
    gif.unlink()
    out = cli("evaluate", "--run-dir", str(studies / "arm"), "--methods", "lazy,td3bc", "--no-figures")
    assert out.returncode == 0, out.stderr[-3000:]
    after = json.loads((studies / "arm" / "results.json").read_text())
    rows = lambda r: {name: (m["per_seed"], m["summary"]) for name, m in r["methods"].items()}
    assert rows(after) == rows(before)  # deterministic, and the other methods' rows kept
    out = cli("plot", "--run-dir", str(studies / "arm"), "--methods", "td3bc")
    assert out.returncode == 0, out.stderr[-3000:]
    assert gif.read_bytes()[:6] == b"GIF89a"
    missing = cli("evaluate", "--run-dir", str(studies / "arm"), "--methods", "naf:tau=0.1")
    assert missing.returncode == 2 and "no trained naf:tau=0.1 here" in missing.stderr
    # lazy Q's policy settings: only where lazy Q is evaluated, and only where they apply
    last = (studies / "arm" / "results.json").read_text()
    other = cli("evaluate", "--run-dir", str(studies / "arm"), "--methods", "td3bc", "--set",
                "neighbours.max_level=3")
    assert other.returncode == 2 and "change lazy Q's policy" in other.stderr
    subgoals = cli("evaluate", "--run-dir", str(studies / "arm"), "--methods", "lazy", "--set",
                   "neighbours.subgoal_steps=5")
    assert subgoals.returncode == 2 and "neighbours.subgoal_steps" in subgoals.stderr, subgoals.stderr[-2000:]
    assert (studies / "arm" / "results.json").read_text() == last  # nothing written


def test_static_resume_equals_the_uninterrupted_run(studies, tmp_path):
    """Lazy Q and a baseline stopped after their first block, and a damaged newest
    checkpoint: resuming (the same programs) ends bitwise where the uninterrupted run did."""
    src = studies / "arm-long"
    copy = tmp_path / "cut"
    shutil.copytree(src, copy)
    config = override(tasks.preset("arm-long", "smoke"), TINY + LONG)
    shutil.rmtree(copy / "lazy" / "checkpoints" / "2")
    td3 = copy / "td3bc" / "checkpoints"
    victim = max((p for p in (td3 / "10" / "state").rglob("*") if p.is_file()), key=lambda p: p.stat().st_size)
    victim.write_bytes(victim.read_bytes()[: victim.stat().st_size // 2])
    for block in range(2, 10):
        shutil.rmtree(td3 / str(block))
    run(config, copy, seeds=[0], methods=["lazy", "td3bc"], resume=True, progress=False)
    assert (copy / "td3bc" / "checkpoints_damaged" / "10").is_dir()  # moved aside, not deleted
    for method in ("lazy", "td3bc"):
        resumed, uninterrupted = load_run(copy, method).states, load_run(src, method).states
        assert all(jax.tree.leaves(jax.tree.map(lambda x, y: bool(np.array_equal(x, y)),
                                                resumed, uninterrupted))), method
    lines = [json.loads(x)["block"] for x in (copy / "lazy" / "metrics.jsonl").read_text().splitlines()]
    assert lines == [1, 2]
    with pytest.raises(CheckpointError, match="damaged or truncated"):
        load_checkpoint(copy / "td3bc" / "checkpoints_damaged", jax.eval_shape(lambda: resumed), 10)


def test_the_dataset_cache_is_reused_only_for_the_same_data(studies, tmp_path):
    config = override(tasks.preset("arm", "smoke"), TINY)
    path = studies / "arm" / "data" / "0" / "dataset.npz"
    stamp = path.stat().st_mtime_ns
    sd = static_data(tasks.get("arm"), config, studies / "arm", [0], progress=False)
    assert path.stat().st_mtime_ns == stamp  # reused
    other = static_data(tasks.get("arm"), override(config, ["collect.n_goals=5"]), tmp_path, [0],
                        progress=False)
    assert other.stacked.g.shape[1] != sd.stacked.g.shape[1] or not np.array_equal(
        np.asarray(other.stacked.g[0, :10]), np.asarray(sd.stacked.g[0, :10]))
    assert jnp.all(sd.stacked.s[0, : int(sd.n_valid[0])] == load_run(studies / "arm").data.stacked.s[0])
