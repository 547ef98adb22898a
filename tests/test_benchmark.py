"""``python -m lazyq_jax benchmark``: a suite's datasets at smoke scale end to end, interrupted
and resumed (a finished dataset is not trained again), its table against the runs' own
results, ``report --suite`` and ``report --archive`` of a benchmark directory."""

import json

import pytest
from conftest import POINTMAZE_SMOKE, cli

from lazyq_jax.config import ConfigError
from lazyq_jax.run import benchmark as bench
from lazyq_jax.run import suite
from lazyq_jax.run.rundir import RunDirError, parse_method
from lazyq_jax.stats import t_interval

GCIVL = "gcivl:steps=4:width=16:batch_size=32"
DATASETS = ["pointmaze-medium-navigate", "pointmaze-large-stitch"]


def test_plan_and_bad_input(tmp_path):
    assert bench.plan("ogbench-pointmaze")[0] == "pointmaze-medium-navigate"
    assert len(bench.plan("ogbench-pointmaze")) == 8
    # OGBench's ids with -v0, in the suite's order whatever the order asked
    assert bench.plan("ogbench-pointmaze", ["pointmaze-large-stitch-v0", "pointmaze-medium-navigate"]) == DATASETS
    with pytest.raises(ConfigError, match="unknown benchmark suite"):
        bench.plan("ogbench-antmaze")
    with pytest.raises(ConfigError, match="not in suite"):
        bench.plan("ogbench-pointmaze", ["pointmaze-huge-navigate"])
    with pytest.raises(ConfigError, match="no dataset chosen"):
        bench.plan("ogbench-pointmaze", [])
    with pytest.raises(RunDirError, match="no suite.json"):
        suite.read_suite(tmp_path)
    # a misspelt method or a bad seed is refused before suite.json records it
    for methods, seeds, match in ((["lazy", "gcilv"], [0], "unknown method"), (["lazy"], [-1], "seeds")):
        with pytest.raises(ConfigError, match=match):
            bench.benchmark("ogbench-pointmaze", tmp_path / "b", seeds, methods, preset="smoke")
        assert not (tmp_path / "b" / suite.SUITE_FILE).exists()
    out = cli("benchmark", "ogbench-pointmaze", "--datasets", ",", "--run-dir", str(tmp_path / "c"))
    assert out.returncode != 0 and "names no dataset" in out.stderr


def test_benchmark_interrupted_resumed_and_reported(tmp_path, monkeypatch):
    run_dir = tmp_path / "bench"
    args = dict(datasets=DATASETS, preset="smoke", sets=POINTMAZE_SMOKE, progress=False, command="test")
    real_run = bench.run

    def interrupted(config, d, **kw):  # the second dataset is cut off before it trains
        if d.name == DATASETS[1]:
            raise KeyboardInterrupt
        return real_run(config, d, **kw)

    monkeypatch.setattr(bench, "run", interrupted)
    with pytest.raises(KeyboardInterrupt):
        bench.benchmark("ogbench-pointmaze", run_dir, [0], ["lazy", GCIVL], **args)
    data = json.loads((run_dir / "results.json").read_text())
    assert [d["pending"] for d in data["datasets"]] == [False, True]
    assert "pending" in (run_dir / "results.md").read_text()
    first = run_dir / DATASETS[0]
    trained = (first / "lazy" / "metrics.jsonl").read_text(), (first / "lazy" / "timings.json").read_text()
    # another suite's settings are refused before anything runs
    with pytest.raises(RunDirError, match="preset"):
        bench.benchmark("ogbench-pointmaze", run_dir, [0], ["lazy"], **{**args, "preset": "paper", "sets": []})
    monkeypatch.setattr(bench, "run", real_run)

    # resumed through the command line: the first dataset only re-evaluated, the second trained
    sets = [a for s in POINTMAZE_SMOKE for a in ("--set", s)]
    out = cli("benchmark", "ogbench-pointmaze", "--datasets", ",".join(DATASETS), "--preset", "smoke",
              "--seeds", "1", "--methods", f"lazy,{GCIVL}", "--run-dir", str(run_dir), "--no-progress", *sets)
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-3000:]
    assert (first / "lazy" / "metrics.jsonl").read_text() == trained[0]
    assert json.loads((first / "lazy" / "timings.json").read_text())["train_s"] == json.loads(trained[1])["train_s"]
    data = json.loads((run_dir / "results.json").read_text())
    assert [d["pending"] for d in data["datasets"]] == [False, False]
    for d in data["datasets"]:
        results = json.loads((run_dir / d["dataset"] / "results.json").read_text())
        for method in ("lazy", GCIVL):
            rates = [row["success_rate"] for row in results["methods"][method]["per_seed"]]
            assert d["methods"][method]["rate"] == t_interval(rates, bounds=(0.0, 1.0))
            assert d["methods"][method]["seeds"] == [0]
        assert d["published"]["qrl"][0] == {"pointmaze-medium-navigate": 82, "pointmaze-large-stitch": 84}[d["dataset"]]
    # the stitch dataset's baseline trained with OGBench's stitch flags and the lazy rows'
    # budget is lazy Q's own steps x batch
    gcivl = json.loads((run_dir / DATASETS[1] / parse_method(GCIVL).dirname / "method.json").read_text())
    assert gcivl["config"]["actor_p_randomgoal"] == 0.5
    md = (run_dir / "results.md").read_text()
    assert md.splitlines()[0] == "| dataset | lazy | " + GCIVL + " | best published |"
    assert "SAW 97 ± 2" in md and "QRL 84 ± 15" in md

    # report --suite writes the same table; --archive copies a benchmark directory whole
    out = cli("report", "--suite", str(run_dir))
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.splitlines()[:4] == md.splitlines()[:4]
    out = cli("report", "--archive", str(tmp_path / "archived"), str(run_dir))
    assert out.returncode == 0, out.stderr[-3000:]
    assert suite.table(tmp_path / "archived", "x")["datasets"] == suite.table(run_dir, "x")["datasets"]


def test_benchmark_adds_seeds_as_a_group(tmp_path):
    """Seeds a benchmark directory does not hold yet train as a new group below each dataset
    (the first group is resumed, not retrained); the table pools the groups' seeds."""
    run_dir = tmp_path / "bench"
    args = dict(preset="smoke", sets=POINTMAZE_SMOKE, progress=False, command="test")
    bench.benchmark("ogbench-pointmaze", run_dir, [0], ["lazy"], datasets=DATASETS, **args)
    first = run_dir / DATASETS[0]
    trained = (first / "lazy" / "metrics.jsonl").read_text()
    bench.benchmark("ogbench-pointmaze", run_dir, [0, 1], ["lazy"], datasets=DATASETS[:1], **args)
    meta = suite.read_suite(run_dir)
    assert meta["seeds"] == [0, 1] and meta["seed_groups"] == [[0], [1]]
    group = suite.group_dir(first, [1], meta["seed_groups"])
    assert group == first / "seeds-1" and json.loads((group / "run.json").read_text())["seeds"] == [1]
    assert (first / "lazy" / "metrics.jsonl").read_text() == trained
    rates = [row["success_rate"] for d in (first, group)
             for row in json.loads((d / "results.json").read_text())["methods"]["lazy"]["per_seed"]]
    data = suite.table(run_dir)
    one, other = data["datasets"]
    assert one["methods"]["lazy"]["seeds"] == [0, 1]
    assert one["methods"]["lazy"]["rate"] == t_interval(rates, bounds=(0.0, 1.0))
    assert other["methods"]["lazy"]["seeds"] == [0]  # not extended: its row says so
    rows = suite.markdown(data).splitlines()
    assert "(1 seed)" not in rows[2] and "(1 seed)" in rows[3] and "seeds 0, 1:" in rows[5]
    out = cli("report", "--archive", str(tmp_path / "archived"), str(run_dir))
    assert out.returncode == 0, out.stderr[-3000:]
    assert (tmp_path / "archived" / DATASETS[0] / "seeds-1" / "results.json").is_file()
    assert suite.table(tmp_path / "archived", "x")["datasets"] == suite.table(run_dir, "x")["datasets"]

    # re-evaluated with other policy settings (evaluate --set records them as "acting"): one
    # seed group alone is refused, the first dataset's both groups label its cell, every
    # dataset the column's head
    def acting(path, settings):
        results = json.loads((path / "results.json").read_text())
        results["methods"]["lazy"]["acting"] = settings
        (path / "results.json").write_text(json.dumps(results))

    far = {"neighbours.far_subgoal_steps": 100}
    acting(group, far)
    with pytest.raises(RunDirError, match="evaluate every seed group alike"):
        suite.table(run_dir)
    acting(first, far)
    rows = suite.markdown(suite.table(run_dir)).splitlines()
    assert rows[0] == "| dataset | lazy | best published |"
    assert "(neighbours.far_subgoal_steps=100)" in rows[2] and "far_subgoal" not in rows[3]
    acting(run_dir / DATASETS[1], far)
    rows = suite.markdown(suite.table(run_dir)).splitlines()
    assert rows[0] == "| dataset | lazy (neighbours.far_subgoal_steps=100) | best published |"
    assert "far_subgoal" not in rows[2] + rows[3]
