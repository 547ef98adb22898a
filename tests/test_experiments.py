"""experiments/: the index names every script and only scripts that exist, every script
answers ``--help``, the cheap ones run a tiny case, the shared helper computes what it says
(against SciPy's t interval) and learned_space.py's map is what it saves (against the network
and NumPy)."""

import re
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
from conftest import timeout
from scipy import stats

EXP = Path(__file__).resolve().parents[1] / "experiments"
sys.path.insert(0, str(EXP))
from _common import alternating, rate_keys, rates_table, timed  # the experiments' shared helper
from learned_space import load_phi, metric_values, phi_net, save_phi, trajectory_pairs

from lazyq_jax.agents.common import init_ensemble

SCRIPTS = sorted(p.name for p in EXP.iterdir() if p.suffix in (".py", ".sh") and not p.name.startswith("_"))
# (script, arguments): seconds each on the 2-core CPU, mostly compilation
TINY = [("bench_lstsq.py", ["--n", "2000", "--loop", "50"]),
        ("bench_train.py", ["--widths", "8", "--rows", "8192", "--batch-sizes", "1024", "--repeats", "1"])]
# one process for all of them: JAX is imported once
RUNNER = """
import runpy, sys
sys.path.insert(0, sys.argv[1])
for argv in eval(sys.argv[2]):
    sys.argv = argv
    try:
        runpy.run_path(argv[0], run_name="__main__")
    except SystemExit as e:
        if e.code not in (0, None):
            raise
    print("@@ran", argv[0].rsplit("/", 1)[-1], flush=True)
"""


def run_scripts(cases: list[tuple[str, list[str]]], seconds: float) -> str:
    argvs = [[str(EXP / name), *args] for name, args in cases]
    out = subprocess.run([sys.executable, "-c", RUNNER, str(EXP), repr(argvs)], capture_output=True,
                         text=True, timeout=timeout(seconds), check=False)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    assert re.findall(r"@@ran (\S+)", out.stdout) == [name for name, _ in cases], out.stdout[-3000:]
    return out.stdout


def test_the_index_lists_every_script_and_names_only_scripts_that_exist():
    index = (EXP / "README.md").read_text()
    listed = set(re.findall(r"^\| `([\w.]+)`", index, re.MULTILINE))
    assert listed == set(SCRIPTS), f"not in the index: {set(SCRIPTS) - listed}; gone: {listed - set(SCRIPTS)}"
    named = re.findall(r"experiments/([\w.]+\.(?:py|sh))", index + (EXP / "device_check.sh").read_text())
    assert named and not [n for n in named if not (EXP / n).exists()]


def test_every_python_script_answers_help():
    out = run_scripts([(name, ["--help"]) for name in SCRIPTS if name.endswith(".py")], seconds=120)
    assert out.count("usage:") == sum(name.endswith(".py") for name in SCRIPTS)


def test_device_check_parses_and_asks_for_a_part():
    assert subprocess.run(["bash", "-n", str(EXP / "device_check.sh")], check=False).returncode == 0
    out = subprocess.run(["bash", str(EXP / "device_check.sh")], capture_output=True, text=True, check=False)
    assert out.returncode != 0 and "usage: device_check.sh" in out.stderr


def test_tiny_cases_run():
    out = run_scripts(TINY, seconds=300)
    assert "fit_local_linear" in out and "GFLOP/s" in out


def test_timed_and_alternating_call_as_they_say():
    calls = []
    out, first, median = timed(lambda x: calls.append(x) or x + 1, 1, repeats=3)
    assert (out, calls) == (2, [1] * 4) and first >= 0 and median >= 0
    order = []
    times = alternating({"a": lambda: order.append("a"), "b": lambda: order.append("b")}, 2)
    assert order == ["a", "b", "a", "b"] and {k: len(v) for k, v in times.items()} == {"a": 2, "b": 2}


def test_rates_table_against_scipy(capsys):
    rng = np.random.default_rng(0)
    first = [{"axis_rate": x, "all_rate": 0.5, "per_direction_correct_rate": 0.1, "long_rate": float("nan")}
             for x in rng.uniform(0.2, 0.8, 5)]
    second = [{**r, "axis_rate": r["axis_rate"] + d} for r, d in zip(first, rng.uniform(0.0, 0.1, 5))]
    assert rate_keys(first[0]) == ["axis_rate", "all_rate"]
    rates_table({"zero": first, "random": second}, ["axis_rate"])
    lines = capsys.readouterr().out.splitlines()
    x = np.array([r["axis_rate"] for r in first])
    d = np.array([b["axis_rate"] - a["axis_rate"] for a, b in zip(first, second)])
    for row, v in ((lines[2], x), (lines[4], d)):
        lo, hi = stats.t.interval(0.95, len(v) - 1, loc=v.mean(), scale=v.std(ddof=1) / np.sqrt(len(v)))
        assert row.endswith(f"{100 * v.mean():.1f} % [{100 * lo:.1f}, {100 * hi:.1f}] |"), row
    assert lines[4].startswith("| random - zero (paired) |")


def test_learned_space_saves_its_map_and_values_by_its_metric(tmp_path):
    """experiments/learned_space.py: the saved map is the twin's first member (against the
    network applied to those parameters), its value is minus the Euclidean distance of the
    maps (against NumPy, both members), and the trajectory pairs stay inside a trajectory."""
    rng = np.random.default_rng(0)
    s, g = (rng.normal(size=(32, 6)).astype(np.float32) for _ in range(2))
    net = phi_net(16, 3, 4)
    params = init_ensemble(net, jax.random.PRNGKey(0), s[:1])
    members = [np.asarray(net.apply(jax.tree.map(lambda x, i=i: x[i], params), s), np.float64) for i in (0, 1)]
    save_phi(tmp_path / "phi.msgpack", net, params)
    # float32 MLP outputs of magnitude ~1, 3 layers of 16: rounding ~1e-6
    np.testing.assert_allclose(np.asarray(load_phi(tmp_path / "phi.msgpack")(s)), members[0], rtol=1e-5, atol=1e-5)
    assert not np.allclose(members[0], members[1])  # two members, independently initialised
    goals = [np.asarray(net.apply(jax.tree.map(lambda x, i=i: x[i], params), g), np.float64) for i in (0, 1)]
    expected = [-np.linalg.norm(a - b, axis=-1) for a, b in zip(members, goals)]
    np.testing.assert_allclose(np.asarray(metric_values(net, params, s, g)), expected, rtol=1e-5, atol=1e-5)
    traj_last = np.repeat(np.arange(9, 100, 10), 10)  # ten trajectories of ten rows
    rows, h = trajectory_pairs(traj_last, 500, 30, rng)
    assert len(rows) == 500 and (h >= 1).all() and (rows + h <= traj_last[rows]).all() and h.max() <= 9
