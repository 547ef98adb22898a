"""Device meshes: config errors here, the multi-device checks in a 4-device process."""

import os
import socket
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

from lazyq_jax.checkpoint import load_checkpoint
from lazyq_jax.config import ConfigError, ParallelConfig, override
from lazyq_jax.data import load_dataset
from lazyq_jax.parallel import check_divisible, force_host_devices, make_mesh
from lazyq_jax.pipeline import mesh_for

from conftest import PUSH


def test_multidevice_results_match_one_device():
    """Dataset and neighbourhoods bitwise, training within bounds derived from what is compared
    (tests/multidevice_check.py).

    XLA_FLAGS must be set before JAX starts, hence a separate process.
    """
    env = {**os.environ, "XLA_FLAGS": "--xla_force_host_platform_device_count=4"}
    script = Path(__file__).with_name("multidevice_check.py")
    proc = subprocess.run([sys.executable, str(script)], env=env, capture_output=True, text=True,
                          timeout=900)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "all multi-device checks passed" in proc.stdout


def test_more_devices_than_exist_is_a_config_error_with_a_hint():
    n = jax.device_count() + 1
    with pytest.raises(ConfigError, match=f"parallel.devices={n} but only .*xla_force_host"):
        make_mesh(n)
    with pytest.raises(ConfigError, match="parallel.devices"):
        mesh_for(override(PUSH, [f"parallel.devices={n}"]))


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
    by hand as on a cluster.  The dataset is bitwise the single-process one, the trained
    parameters within the Adam bound of a few steps, and files are written once."""
    # 4 Adam steps (one epoch of 4 minibatches of 1024): too few for the chaos of training
    # to amplify rounding (see tests/test_study.py), so the Adam bound below applies.
    args = [sys.executable, "-m", "lazyq_jax", "train", "--preset", "smoke", "--no-eval",
            "--no-progress", "--set", "collect.n_starts=120", "--set", "train.cycles=1",
            "--set", "train.epochs=1", "--set", "train.batch_size=1024"]
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    port = _free_port()
    procs = [subprocess.Popen(args + ["--run-dir", str(tmp_path / "multi")], stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True,
                              env={**env, "LAZYQ_DISTRIBUTED": "1", "JAX_NUM_PROCESSES": "2",
                                   "JAX_PROCESS_ID": str(i),
                                   "JAX_COORDINATOR_ADDRESS": f"127.0.0.1:{port}"})
             for i in range(2)]
    try:
        logs = [p.communicate(timeout=600)[0] for p in procs]
    finally:
        for p in procs:
            p.kill()
    for i, (p, log) in enumerate(zip(procs, logs)):
        assert p.returncode == 0, f"process {i}:\n{log}"
    assert "on 2 processes" in logs[0]
    single = subprocess.run(args + ["--run-dir", str(tmp_path / "single")], env=env,
                            capture_output=True, text=True, timeout=600)
    assert single.returncode == 0, single.stdout + single.stderr

    multi_data, _, _ = load_dataset(tmp_path / "multi" / "dataset.npz")
    single_data, _, _ = load_dataset(tmp_path / "single" / "dataset.npz")
    for a, b in zip(jax.tree.leaves(multi_data), jax.tree.leaves(single_data)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    multi_state, _ = load_checkpoint(tmp_path / "multi" / "checkpoints")
    single_state, _ = load_checkpoint(tmp_path / "single" / "checkpoints")
    diff = max(float(np.abs(np.asarray(a) - np.asarray(b)).max()) for a, b in
               zip(jax.tree.leaves(multi_state.params), jax.tree.leaves(single_state.params)))
    # Adam moves a parameter by at most ~lr per step: gradients that differ by a relative
    # rho (1e-6 for reduction order, ~1 for a wrong shard) give lr * steps * rho; rho = 1e-3.
    _, config = load_checkpoint(tmp_path / "single" / "checkpoints")
    steps = config.train.epochs * (single_data.size // config.train.batch_size)
    assert steps >= 3
    assert diff < config.train.learning_rate * steps * 1e-3, (diff, steps)
    lines = (tmp_path / "multi" / "metrics.jsonl").read_text().splitlines()
    assert len(lines) == 1, lines  # one writer
