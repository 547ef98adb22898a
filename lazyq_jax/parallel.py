"""Devices: the one-axis mesh every phase shards over, multi-host start-up, host reads.

The whole pipeline uses JAX's own SPMD machinery over a 1-D :class:`jax.sharding.Mesh`
with axis ``"data"``:

* collection and the neighbour search use ``jax.shard_map``: every device runs the
  *same* per-device program on its block of episodes / queries, so the results are
  bitwise the same for any device count (the plain SPMD partitioner lowers a
  differently-shaped program, which the contact dynamics amplified to 3e-4);
* training runs each epoch in ``shard_map``: parameters are replicated, every device
  takes its share of each minibatch, and ``pmean`` averages the gradients, the loss
  and the batch-norm statistics (synchronised batch norm: the statistics of the
  whole minibatch, as on one device);
* the targets use ``jit`` with sharding constraints (value chunks split over the
  devices, fits split by rows).

``mesh=None`` anywhere means "no sharding annotations": the single-device code path.
"""

from __future__ import annotations

import os
from typing import Callable

import jax
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

from lazyq_jax.config import ConfigError, ParallelConfig

AXIS = "data"
HOST_DEVICES_ENV = "LAZYQ_HOST_DEVICES"
DISTRIBUTED_ENV = "LAZYQ_DISTRIBUTED"


def force_host_devices(n: int | None = None) -> None:
    """Ask XLA for ``n`` CPU devices (default: ``$LAZYQ_HOST_DEVICES``, if set).

    Must run before JAX initialises its backends (the first computation or
    ``jax.devices()``); it does nothing if ``XLA_FLAGS`` already sets a count.
    """
    if n is None:
        raw = os.environ.get(HOST_DEVICES_ENV, "")
        if not raw:
            return
        if not raw.isdigit() or int(raw) < 1:
            raise ConfigError(f"{HOST_DEVICES_ENV}={raw!r} must be an integer >= 1")
        n = int(raw)
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_force_host_platform_device_count" not in flags:
        os.environ["XLA_FLAGS"] = f"{flags} --xla_force_host_platform_device_count={n}".strip()


COMPILE_CACHE_ENV = "LAZYQ_COMPILE_CACHE"


def enable_compilation_cache(path: str | None = None) -> str | None:
    """Turn on JAX's persistent compilation cache (what the CLI does at start-up).

    ``path`` defaults to ``$LAZYQ_COMPILE_CACHE``, else ``$XDG_CACHE_HOME/lazyq-jax/jax``
    (``~/.cache/lazyq-jax/jax``); ``LAZYQ_COMPILE_CACHE=off`` (or ``0``) leaves it off.
    Programs that took at least 0.5 s to compile are stored there and reloaded by
    later processes with the same JAX version, devices and flags.  Returns the
    directory, or None when off.  Library imports never do this by themselves.
    """
    raw = os.environ.get(COMPILE_CACHE_ENV, "") if path is None else path
    if raw.strip().lower() in ("off", "0", "false", "no"):
        return None
    if not raw:
        base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
        raw = os.path.join(base, "lazyq-jax", "jax")
    jax.config.update("jax_compilation_cache_dir", raw)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
    return raw


def maybe_initialize_distributed(config: ParallelConfig) -> bool:
    """``jax.distributed.initialize()`` if ``config.distributed`` or ``$LAZYQ_DISTRIBUTED``.

    Call it before anything else touches JAX.  Returns whether it initialised.
    """
    wanted = config.distributed or os.environ.get(DISTRIBUTED_ENV, "") in ("1", "true", "yes")
    if not wanted or jax.distributed.is_initialized():
        return False
    # jax reads JAX_COORDINATOR_ADDRESS itself; the process count and id only on clusters
    # it detects (SLURM, Open MPI, TPU), so a hand launch passes them through these.
    counts = {}
    for name, arg in (("JAX_NUM_PROCESSES", "num_processes"), ("JAX_PROCESS_ID", "process_id")):
        raw = os.environ.get(name)
        if raw is not None:
            if not raw.isdigit():
                raise ConfigError(f"{name}={raw!r} must be a non-negative integer")
            counts[arg] = int(raw)
    jax.distributed.initialize(**counts)
    return True


def make_mesh(devices: int | ParallelConfig = 0) -> Mesh:
    """A 1-D mesh (axis ``"data"``) over the first ``devices`` devices (0: all).

    Raises :class:`ConfigError` (before anything compiles) if more devices are
    asked for than exist, or, with several processes, for a subset of the devices.
    """
    if isinstance(devices, ParallelConfig):
        devices = devices.devices
    if not isinstance(devices, int) or isinstance(devices, bool) or devices < 0:
        raise ConfigError(f"devices must be an integer >= 0 (0: all), got {devices!r}")
    available = jax.devices()
    n = devices or len(available)
    if n > len(available):
        hint = (f"; on CPU, start with XLA_FLAGS=--xla_force_host_platform_device_count={n} "
                f"(or {HOST_DEVICES_ENV}={n} for the lazyq-jax CLI)"
                if available[0].platform == "cpu" else "")
        raise ConfigError(f"parallel.devices={n} but only {len(available)} "
                          f"{available[0].platform} device(s) exist{hint}")
    if jax.process_count() > 1 and n != len(available):
        raise ConfigError(f"parallel.devices={n}: with {jax.process_count()} processes the mesh "
                          f"must span all {len(available)} devices; use parallel.devices=0")
    return Mesh(np.array(available[:n]), (AXIS,))


def mesh_size(mesh: Mesh | None) -> int:
    return 1 if mesh is None else mesh.size


def check_divisible(what: str, value: int, mesh: Mesh | None) -> None:
    """Fail before compiling when ``value`` cannot be split evenly over the mesh."""
    d = mesh_size(mesh)
    if value % d:
        lower, upper = value // d * d, -(-value // d) * d
        raise ConfigError(f"{what}={value} is not divisible by the {d} devices of the mesh; "
                          f"use a multiple of {d} (e.g. {lower or upper} or {upper}) or set "
                          f"parallel.devices to a divisor of {value}")


def replicated(mesh: Mesh | None):
    return None if mesh is None else NamedSharding(mesh, P())


def sharded(mesh: Mesh | None):
    """``NamedSharding(mesh, P("data"))`` (split along the first axis), or ``None``."""
    return None if mesh is None else NamedSharding(mesh, P(AXIS))


def constrain(x, sharding):
    """``with_sharding_constraint`` on every leaf, or ``x`` unchanged without a sharding."""
    if sharding is None:
        return x
    return jax.tree.map(lambda leaf: jax.lax.with_sharding_constraint(leaf, sharding), x)


def put(x, sharding):
    """``jax.device_put(x, sharding)`` for a pytree of host or device arrays (any process count).

    With several processes every process must pass the same global ``x``.
    """
    if sharding is None:
        return x
    if jax.process_count() == 1:
        return jax.device_put(x, sharding)
    def one(leaf):
        host = np.asarray(leaf)
        return jax.make_array_from_callback(host.shape, sharding, lambda index: host[index])

    return jax.tree.map(one, x)


def to_host(x):
    """A pytree of (possibly sharded, possibly multi-host) arrays as NumPy on every process."""
    def one(leaf):
        if not isinstance(leaf, jax.Array) or leaf.is_fully_addressable:
            return np.asarray(leaf)
        if leaf.is_fully_replicated:
            return np.asarray(leaf.addressable_data(0))
        return np.asarray(multihost_utils.process_allgather(leaf, tiled=True))

    return jax.tree.map(one, x)


def over_seeds(fn: Callable, n_seeds: int) -> Callable:
    """``jax.jit(jax.vmap(fn))`` for arguments stacked over ``n_seeds`` seeds.

    For a single seed the leading axis is dropped and ``fn`` runs unbatched: XLA's CPU
    kernels for a batch of one were measured 2-3x slower than the unbatched ones (a
    paper-scale epoch 4.9 s vs 1.75 s), while for 8 seeds the batched epoch costs the
    same per seed as one unbatched epoch (README, Performance).
    """
    if n_seeds > 1:
        return jax.jit(jax.vmap(fn))
    one = jax.jit(fn)
    unbatched = lambda *args: jax.tree.map(lambda x: x[None], one(*jax.tree.map(lambda x: x[0], args)))
    unbatched.jitted = one  # the compiled function (e.g. to count its programs)
    return unbatched


def is_main_process() -> bool:
    """Process 0 writes the files that are not checkpoints (orbax coordinates those)."""
    return jax.process_index() == 0


def barrier(name: str) -> None:
    """Wait until every process gets here (nothing to do with one process)."""
    if jax.process_count() > 1:
        multihost_utils.sync_global_devices(name)
