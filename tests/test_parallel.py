"""Device meshes: config errors here, the multi-device checks in a 4-device process."""

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

from lazyq_jax.config import ConfigError, ParallelConfig, override
from lazyq_jax.data import load_dataset
from lazyq_jax.neighbours import find_neighbours
from lazyq_jax.parallel import check_divisible, force_host_devices, make_mesh
from lazyq_jax.run import run

from conftest import PUSH, timeout
from two_process_search import search_inputs


def test_multidevice_results_match_one_device():
    """Dataset and neighbourhoods bitwise, training within bounds derived from what is compared
    (tests/multidevice_check.py).

    XLA_FLAGS must be set before JAX starts, hence a separate process.
    """
    env = {**os.environ, "XLA_FLAGS": "--xla_force_host_platform_device_count=4"}
    script = Path(__file__).with_name("multidevice_check.py")
    proc = subprocess.run([sys.executable, str(script)], env=env, capture_output=True, text=True,
                          timeout=timeout(900))
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "all multi-device checks passed" in proc.stdout


def test_more_devices_than_exist_is_a_config_error_with_a_hint():
    n = jax.device_count() + 1
    with pytest.raises(ConfigError, match=f"parallel.devices={n} but only .*xla_force_host"):
        make_mesh(n)
    with pytest.raises(ConfigError, match="parallel.devices"):  # before anything is written
        run(override(PUSH, [f"parallel.devices={n}"]), "/nonexistent/never/written")


@pytest.mark.parametrize("bad", [-1, 1.5, True, "2"])
def test_bad_device_counts_are_refused(bad):
    with pytest.raises(ConfigError, match="devices"):
        ParallelConfig(devices=bad)


def test_indivisible_sizes_name_the_field_and_a_fix():
    class FakeMesh:
        size = 4

    with pytest.raises(ConfigError, match=r"train.batch_size=66 .* 4 devices.*e\.g\. 64 or 68"):
        check_divisible("train.batch_size", 66, FakeMesh())
    check_divisible("train.batch_size", 64, FakeMesh())


def test_host_device_variable_is_validated(monkeypatch):
    monkeypatch.setenv("LAZYQ_HOST_DEVICES", "two")
    with pytest.raises(ConfigError, match="LAZYQ_HOST_DEVICES='two'"):
        force_host_devices()
    monkeypatch.setenv("XLA_FLAGS", "--xla_force_host_platform_device_count=3")
    force_host_devices(2)  # an explicit XLA_FLAGS count wins
    assert os.environ["XLA_FLAGS"] == "--xla_force_host_platform_device_count=3"


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def test_two_processes_match_one_process(tmp_path):
    """Multi-host on one machine: 2 processes (1 CPU device each, gloo collectives) launched
    by hand as on a cluster.  The dataset is bitwise the single-process one; the first
    cycle's loss at the initial parameters and its targets (from the frozen network) agree
    within float32 rounding of their means; files are written once.  One Adam step only:
    training outcomes of the two programs are not compared (training is chaotic)."""
    args = [sys.executable, "-m", "lazyq_jax", "train", "--preset", "smoke", "--no-eval",
            "--no-progress", "--set", "collect.n_starts=120", "--set", "train.cycles=1",
            "--set", "train.epochs=1", "--set", "train.batch_size=8192"]
    env = {**{k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}, "LAZYQ_COMPILE_CACHE": "off"}
    port = _free_port()
    procs = [subprocess.Popen(args + ["--run-dir", str(tmp_path / "multi")], stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True,
                              env={**env, "LAZYQ_DISTRIBUTED": "1", "JAX_NUM_PROCESSES": "2",
                                   "JAX_PROCESS_ID": str(i),
                                   "JAX_COORDINATOR_ADDRESS": f"127.0.0.1:{port}"})
             for i in range(2)]
    try:
        logs = [p.communicate(timeout=timeout(600))[0] for p in procs]
    finally:
        for p in procs:
            p.kill()
    for i, (p, log) in enumerate(zip(procs, logs)):
        assert p.returncode == 0, f"process {i}:\n{log}"
    assert "2 cpu devices" in logs[0]
    single = subprocess.run(args + ["--run-dir", str(tmp_path / "single")], env=env,
                            capture_output=True, text=True, timeout=timeout(600))
    assert single.returncode == 0, single.stdout + single.stderr

    multi_data, _ = load_dataset(tmp_path / "multi" / "data" / "0" / "dataset.npz")
    single_data, _ = load_dataset(tmp_path / "single" / "data" / "0" / "dataset.npz")
    for a, b in zip(jax.tree.leaves(multi_data), jax.tree.leaves(single_data)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    read = lambda d: [json.loads(x) for x in (d / "lazy" / "metrics.jsonl").read_text().splitlines()]
    multi, one = read(tmp_path / "multi"), read(tmp_path / "single")
    assert len(multi) == 1, multi  # one writer
    n = single_data.size
    assert n <= 8192  # one minibatch: the first epoch's loss is at the initial parameters
    rtol = n * 2.0 ** -24  # float32 means over n rows summed in another order
    for name in ("loss_first_epoch", "target_mean", "target_std", "beta_norm_mean"):
        np.testing.assert_allclose(multi[0][name], one[0][name], rtol=max(rtol, 1e-5), err_msg=name)
    np.testing.assert_allclose(multi[0]["clip_fraction"], one[0]["clip_fraction"], atol=2 / n + 1e-5)


def test_two_processes_search_general_spaces_like_one(tmp_path):
    """The general neighbour search (3-D states, vector goals, levels > 3) over a mesh of two
    processes with 2 CPU devices each (each process searches on its own devices): both
    processes get bitwise the neighbourhoods of one process without a mesh."""
    script = Path(__file__).parent / "two_process_search.py"
    env = {**os.environ, "XLA_FLAGS": "--xla_force_host_platform_device_count=2",
           "LAZYQ_COMPILE_CACHE": "off", "JAX_NUM_PROCESSES": "2",
           "JAX_COORDINATOR_ADDRESS": f"127.0.0.1:{_free_port()}"}
    out = tmp_path / "search"
    procs = [subprocess.Popen([sys.executable, str(script), str(out)], stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True, env={**env, "JAX_PROCESS_ID": str(i)})
             for i in range(2)]
    try:
        logs = [p.communicate(timeout=timeout(300))[0] for p in procs]
    finally:
        for p in procs:
            p.kill()
    for i, (p, log) in enumerate(zip(procs, logs)):
        assert p.returncode == 0, f"process {i}:\n{log}"
    key, s, g, kw = search_inputs()
    ref = find_neighbours(key, s, g, s, g, **kw)
    assert int(np.asarray(ref.level).max()) > 3
    for i in range(2):
        got = np.load(f"{out}.{i}.npz")
        np.testing.assert_array_equal(got["idx"], np.asarray(ref.idx), err_msg=f"process {i}")
        np.testing.assert_array_equal(got["level"], np.asarray(ref.level), err_msg=f"process {i}")
