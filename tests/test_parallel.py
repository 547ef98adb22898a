"""Device meshes: config errors here, the multi-device checks in a 4-device process."""

import os
import subprocess
import sys
from pathlib import Path

import jax
import pytest

from lazyq_jax.config import ConfigError, ParallelConfig, override
from lazyq_jax.parallel import check_divisible, force_host_devices, make_mesh
from lazyq_jax.pipeline import mesh_for

from conftest import PUSH


def test_multidevice_results_match_one_device():
    """Dataset and neighbourhoods bitwise, training within 1e-5 (tests/multidevice_check.py).

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


def test_default_mesh_spans_all_devices():
    assert make_mesh().size == jax.device_count() == make_mesh(ParallelConfig()).size


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
