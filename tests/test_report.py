"""``python -m lazyq_jax report`` (:mod:`lazyq_jax.run.report`) on run directories made in
tmp by the package's own writers (``open_run``'s run.json, ``write_results``' results.json
from synthetic per-seed evaluations of the real push task): means and intervals against
SciPy's t interval, seeds pooled, settings told apart, paired differences by hand, the
JSON and Markdown forms, archives, and report blocks checked and rewritten.  Nothing trains."""

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from lazyq_jax import tasks
from lazyq_jax.cli import main
from lazyq_jax.config import override
from lazyq_jax.run import report, results
from lazyq_jax.run.rundir import RunDirError, open_run, write_json
from lazyq_jax.stats import format_ci

TASK = tasks.get("push")
GOALS = np.arange(8) * np.pi / 4  # axis goals at even, diagonal goals at odd indices
EPISODES = 10  # per goal


def counts(seed: int, method: str) -> np.ndarray:
    """Synthetic protocol A outcomes ``[goal, (correct, wrong, not pushed)]`` of a seed."""
    correct = np.random.default_rng([seed, len(method)]).integers(0, EPISODES + 1, len(GOALS))
    return np.stack([correct, (EPISODES - correct) // 2, EPISODES - correct - (EPISODES - correct) // 2], 1)


def make_run(run_dir: Path, seeds, methods=("lazy", "iql"), sets=(), acting=None, train_s=30.0, baseline=None):
    """A finished run as the runner leaves it (minus checkpoints, data and figures)."""
    config = override(tasks.preset("push", "smoke"), list(sets))
    open_run(run_dir, config, seeds, resume=False, overwrite=False)
    records = {}
    for name in methods:
        per_seed = [{"seed": s, "protocol_a": {"per_goal": [
            {"goal": float(g), **dict(zip(("correct", "wrong", "not_pushed"), map(int, c)))}
            for g, c in zip(GOALS, counts(s, name))]}} for s in seeds]
        timings = {"train_s": train_s, "prepare_s": 6.0, "steps": 500}
        records[name] = {"per_seed_eval": per_seed, "timings": timings,
                         **({"acting": acting} if acting and name == "lazy" else {})}
        record = ({"method": "lazy", "train": {"epochs": 2, "batch_size": 256}} if name == "lazy" else
                  {"method": name, "config": {"steps": 500, "batch_size": 256, "gamma": 0.99, **(baseline or {})},
                   "budget": 1.0})
        write_json(run_dir / name / "method.json", record)
        write_json(run_dir / name / "timings.json", timings)
        write_json(run_dir / name / "eval.json", {"acting": acting or {}, "per_seed": per_seed} if acting and
                   name == "lazy" else {"per_seed": per_seed})
    summaries = [{"reward_by_goal_octant": [{"positive": 1}] * 8, "moves_that_moved_disk": 1, "rows": 100}
                 for _ in seeds]
    results.write_results(TASK, run_dir, seeds, summaries, records)
    return run_dir


@pytest.fixture(autouse=True)
def no_figures(monkeypatch):
    monkeypatch.setattr(results.plots, "study_per_direction", lambda *a: None)
    monkeypatch.setattr(results.plots, "study_methods", lambda *a: None)


def args(*argv):
    return report.arguments().parse_args([str(a) for a in argv])


def t_reference(values, clip=True):
    """Student's t interval by hand (SciPy's quantile), independent of lazyq_jax.stats."""
    x = np.asarray(values, float)
    half = stats.t.ppf(0.975, len(x) - 1) * x.std(ddof=1) / np.sqrt(len(x))
    lo, hi = x.mean() - half, x.mean() + half
    return x.mean(), (max(lo, 0), min(hi, 1)) if clip else (lo, hi)


def test_seeds_pool_over_runs_and_match_the_t_interval(tmp_path):
    make_run(tmp_path / "a", [0, 1, 2])
    make_run(tmp_path / "b", [5, 3], sets=["seed=5", "parallel.devices=1"], train_s=10.0)  # pooled
    data = report.table(args(tmp_path / "a", tmp_path / "b", "--methods", "lazy,iql"))
    assert [r["label"] for r in data["rows"]] == ["lazy", "iql"]
    for row in data["rows"]:
        assert row["seeds"] == [0, 1, 2, 3, 5]
        c = np.array([counts(s, row["method"]) for s in row["seeds"]])  # [seed, goal, outcome]
        per_seed = {"axis_correct_rate": c[:, 0::2, 0].sum(1) / (4 * EPISODES),
                    "diagonal_correct_rate": c[:, 1::2, 0].sum(1) / (4 * EPISODES),
                    "overall_correct_rate": c[:, :, 0].sum(1) / (8 * EPISODES)}
        for key, values in per_seed.items():
            mean, (lo, hi) = t_reference(values)
            got = row["rates"][key]
            np.testing.assert_allclose([got["mean"], *got["ci95"]], [mean, lo, hi], rtol=1e-12)
        assert row["rates"]["long_horizon_success_rate"] is None  # no protocol B in these runs
        np.testing.assert_allclose(row["train_s_per_seed"], (3 * 36 / 3 + 2 * 16 / 2) / 5)
    assert data["rows"][0]["budget"] == "500 steps x 256 (3 cycles x 2 epochs)"
    assert data["rows"][1]["budget"] == "500 steps x 256"


def test_a_seed_in_two_runs_and_bad_inputs_are_refused(tmp_path, capsys):
    make_run(tmp_path / "a", [0, 1])
    make_run(tmp_path / "b", [1, 2])
    with pytest.raises(RunDirError, match=r"lazy: seed 1 is in .*a and in .*b: which would count"):
        report.table(args(tmp_path / "a", tmp_path / "b"))
    (tmp_path / "maze").mkdir()
    open_run(tmp_path / "maze", tasks.preset("pointmaze", "smoke"), [0], resume=False, overwrite=False)
    write_json(tmp_path / "maze" / "results.json", {"task": "pointmaze", "seeds": [0], "methods": {}})
    (tmp_path / "empty").mkdir()
    for argv, message in [((tmp_path / "empty",), "empty: no results.json"),
                          ((tmp_path / "a", "--methods", "lazy,cql"), "cql: in none of the runs; their methods: lazy, iql"),
                          ((tmp_path / "a", tmp_path / "maze"), "different tasks .*a: push, .*maze: pointmaze")]:
        with pytest.raises(SystemExit) as exit_:
            main(["report", *map(str, argv)])
        assert exit_.value.code == 2
        assert re.search(message, capsys.readouterr().err), message


def test_settings_that_differ_give_labelled_rows_and_paired_differences(tmp_path):
    make_run(tmp_path / "one", [0, 1, 2], sets=["train.target_steps=1"])
    make_run(tmp_path / "ten", [0, 1], sets=["train.target_steps=10"], methods=("lazy",))
    make_run(tmp_path / "flat", [3, 4], sets=["train.target_steps=1"], methods=("lazy",),
             acting={"neighbours.max_level": 2})
    data = report.table(args(tmp_path / "one", tmp_path / "ten", tmp_path / "flat", "--paired"))
    labels = {r["label"]: r["seeds"] for r in data["rows"]}
    assert labels == {"lazy (train.target_steps=1)": [0, 1, 2], "lazy (train.target_steps=10)": [0, 1],
                      "lazy (train.target_steps=1, neighbours.max_level=2)": [3, 4],
                      "iql": [0, 1, 2]}  # lazy Q's settings do not label a baseline's row
    ten = next(p for p in data["paired"] if p["label"] == "lazy (train.target_steps=10)")
    assert ten["reference"] == "lazy (train.target_steps=1)" and ten["seeds"] == [0, 1]
    iql = next(p for p in data["paired"] if p["label"].startswith("iql"))
    diff = [(counts(s, "iql")[:, 0].sum() - counts(s, "lazy")[:, 0].sum()) / (8 * EPISODES) for s in (0, 1, 2)]
    mean, (lo, hi) = t_reference(diff, clip=False)
    got = iql["differences"]["overall_correct_rate"]
    np.testing.assert_allclose([got["mean"], *got["ci95"]], [mean, lo, hi], rtol=1e-9, atol=1e-12)
    text = report.markdown(data)
    assert f"| {100 * mean:.1f} [{100 * lo:.1f}, {100 * hi:.1f}] |" in text.split("Paired")[1]
    flat = next(p for p in data["paired"] if "max_level" in p["label"])
    assert flat["seeds"] == [] and set(flat["differences"].values()) == {None}
    # a baseline's own config (its method.json) does label its rows
    make_run(tmp_path / "g", [5], methods=("iql",), sets=["train.target_steps=1"], baseline={"gamma": 0.9})
    rows = report.table(args(tmp_path / "one", tmp_path / "ten", tmp_path / "g"))["rows"]
    assert {r["label"]: r["seeds"] for r in rows if r["label"].startswith("iql")} == {
        "iql (gamma=0.99)": [0, 1, 2], "iql (gamma=0.9)": [5]}


def test_markdown_json_per_goal_and_the_archive(tmp_path):
    make_run(tmp_path / "a", [0, 1])
    (tmp_path / "a" / "lazy" / "checkpoints" / "1").mkdir(parents=True)  # never archived
    (tmp_path / "a" / "data" / "0").mkdir(parents=True)
    (tmp_path / "a" / "data" / "0" / "summary.json").write_text("{}")
    out = tmp_path / "table.json"
    assert main(["report", str(tmp_path / "a"), "--per-goal", "--format", "json", "--out", str(out)]) == 0
    data = json.loads(out.read_text())
    assert data == report.table(args(tmp_path / "a", "--per-goal"))
    assert data["command"] == f"python -m lazyq_jax report {tmp_path / 'a'} --per-goal"
    for row in data["rows"]:
        total = sum(counts(s, row["method"]) for s in (0, 1))
        assert data["per_goal"][row["label"]] == {f"{np.degrees(g):.1f}": c.tolist() for g, c in zip(GOALS, total)}
    text = report.markdown(data)
    lines = text.splitlines()
    assert lines[0] == ("| method | axis goals correct | diagonal goals correct | all goals correct | "
                        "long horizon reached | seeds | budget | train s / seed |")
    cells = [format_ci(data["rows"][0]["rates"][k]) for k in ("axis_correct_rate", "diagonal_correct_rate",
                                                                       "overall_correct_rate")]
    assert lines[2] == f"| lazy | {' | '.join(cells)} | – | 2 | 500 steps x 256 (3 cycles x 2 epochs) | 18 |"
    assert f"Task push, seeds 0, 1; mean [{results.CI}]" in text and f"`{data['command']}`" in text
    assert "| all | " in text and f"| 45.0 | {' / '.join(map(str, (counts(0, 'lazy') + counts(1, 'lazy'))[1]))} |" in text

    copies = report.archive(tmp_path / "kept", tmp_path / "a")
    assert sorted(str(c.relative_to(tmp_path / "kept")) for c in copies) == sorted(
        ["run.json", "results.json", *(f"{m}/{f}" for m in ("lazy", "iql")
                                       for f in ("method.json", "timings.json", "eval.json"))])
    kept = report.table(args(tmp_path / "kept", "--per-goal"))
    assert {**kept, "command": "", "rows": [{**r, "runs": []} for r in kept["rows"]]} == {
        **data, "command": "", "rows": [{**r, "runs": []} for r in data["rows"]]}


def test_report_blocks_are_checked_and_updated(tmp_path, monkeypatch, capsys):
    repo = tmp_path / "repo"
    (repo / ".git").mkdir(parents=True)
    make_run(repo / "results" / "push", [0, 1])
    doc = repo / "docs" / "push.md"
    doc.parent.mkdir()
    doc.write_text("# Push\n\n<!-- report results/push --methods lazy -->\n<!-- /report -->\n\nafter\n")
    monkeypatch.chdir(tmp_path)  # block paths are relative to the repository root, not the cwd
    assert main(["report", "--check", str(doc)]) == 1
    assert f"{doc}:3: <!-- report results/push --methods lazy -->: differs" in capsys.readouterr().err
    assert main(["report", "--update", str(doc)]) == 0
    text = doc.read_text()
    expected = report.render(args("results/push", "--methods", "lazy"), root=repo)
    assert text == f"# Push\n\n<!-- report results/push --methods lazy -->\n{expected}<!-- /report -->\n\nafter\n"
    assert "`python -m lazyq_jax report results/push --methods lazy`" in text
    assert main(["report", "--check", str(doc)]) == 0
    cell = expected.splitlines()[2].split(" | ")[1]  # lazy's axis rate, e.g. "52.5 % [..]"
    doc.write_text(text.replace(cell, "0.0 % [0.0, 0.1]", 1))  # a number changed by hand
    assert doc.read_text() != text and main(["report", "--check", str(doc)]) == 1
    assert main(["report", "--update", str(doc)]) == 0 and doc.read_text() == text
    shutil.rmtree(repo / "results")
    assert main(["report", "--check", str(doc)]) == 1
    assert f"{doc}:3: <!-- report results/push --methods lazy -->: " in capsys.readouterr().err


def test_the_repositorys_report_blocks_are_current():
    """Every table in the README and docs/ that a report block holds is what its runs give."""
    root = Path(__file__).resolve().parents[1]
    differ, errors = report.blocks([root / "README.md", *sorted((root / "docs").glob("*.md"))])
    assert differ == [] and errors == [], "\n".join(differ + errors + [
        "regenerate: python -m lazyq_jax report --update README.md docs/*.md"])
