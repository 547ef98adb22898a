"""Scouting for the multi-device issue: the collection batch sharded over host devices.

Runs the paper-scale collection kernel (5000 episodes, float64 MJX) once with the
episode keys on 1 device and once sharded over N host devices (XLA's SPMD
partitioner splits the vmapped batch), each in its own process because
``XLA_FLAGS`` must be set before JAX starts.  Prints compile and steady-state
times and how far the two datasets differ.  Not part of the library yet.

    .venv/bin/python experiments/scout_sharded_collect.py [--devices 2]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time


def worker(n_dev: int, out: str) -> None:
    os.environ["XLA_FLAGS"] = f"--xla_force_host_platform_device_count={n_dev}"
    import jax
    import numpy as np
    from jax.sharding import Mesh, NamedSharding, PartitionSpec

    from lazyq_jax.config import CollectConfig
    from lazyq_jax.data import _episode_keys, make_episode_fn
    from lazyq_jax.env import PushEnv

    cfg = CollectConfig()
    mesh = Mesh(np.array(jax.devices()), ("d",))
    with jax.enable_x64(True):
        run = jax.jit(jax.vmap(make_episode_fn(PushEnv(cfg.push), cfg)))
        keys = jax.device_put(_episode_keys(jax.random.PRNGKey(0), 0, cfg.n_starts),
                              NamedSharding(mesh, PartitionSpec("d")))
        t = time.perf_counter()
        jax.block_until_ready(run(keys))
        first = time.perf_counter() - t
        times = []
        for _ in range(3):
            t = time.perf_counter()
            result = jax.block_until_ready(run(keys))
            times.append(time.perf_counter() - t)
    np.savez(out, delta=np.asarray(result["delta"]), r=np.asarray(result["r"]))
    print(f"{n_dev} device(s): first call {first:.2f} s, steady {sorted(times)[1]:.2f} s")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--devices", type=int, default=2)
    ap.add_argument("--worker", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--out", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        worker(args.worker, args.out)
        return
    import numpy as np

    with tempfile.TemporaryDirectory() as tmp:
        files = {}
        for n in (1, args.devices):
            files[n] = os.path.join(tmp, f"d{n}.npz")
            subprocess.run([sys.executable, __file__, "--worker", str(n), "--out", files[n]],
                           check=True)
        a, b = np.load(files[1]), np.load(files[args.devices])
        diff = np.abs(a["delta"] - b["delta"]).max(axis=(1, 2))
        print(f"disk displacements: {int((diff > 0).sum())} of {diff.size} episodes differ, "
              f"{int((diff > 1e-6).sum())} by > 1e-6, max {diff.max():.1e}; reward rows that "
              f"differ: {int((a['r'] != b['r']).sum())} of {a['r'].size}")


if __name__ == "__main__":
    main()
