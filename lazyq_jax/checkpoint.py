"""Per-cycle orbax checkpoints of a :class:`TrainState`, with the run config beside them.

Layout: ``<run_dir>/checkpoints/<cycle>/{state, meta}``; ``meta`` is JSON holding the
checkpoint format version and the full :class:`Config`.  Restores go against an
abstract target built from that config (shapes and dtypes only) and land on this
machine's default device, so a checkpoint written on a GPU reloads on a CPU laptop.
"""

from __future__ import annotations

import os
from pathlib import Path

import jax
import jax.numpy as jnp
import orbax.checkpoint as ocp

from lazyq_jax.config import Config, ConfigError, from_dict, to_dict
from lazyq_jax.train import TrainState, make_train_for

CHECKPOINT_VERSION = 2  # 2: hidden Dense layers without bias


class CheckpointError(ValueError):
    """A checkpoint is missing, partial, or does not fit the requested config."""


def _manager(directory: Path, read_only: bool = False) -> ocp.CheckpointManager:
    # (orbax's read_only mode logs warnings on every open; create=False is enough.)
    options = ocp.CheckpointManagerOptions(max_to_keep=None, create=not read_only,
                                           enable_async_checkpointing=False)
    return ocp.CheckpointManager(directory.absolute(), options=options, item_names=("state", "meta"))


def save_checkpoint(directory: str | os.PathLike, state: TrainState, config: Config) -> Path:
    """Save ``state`` as checkpoint number ``state.cycle`` under ``directory``."""
    directory = Path(directory)
    cycle = int(state.cycle)
    meta = {"version": CHECKPOINT_VERSION, "cycle": cycle, "config": to_dict(config)}
    with _manager(directory) as manager:
        manager.save(cycle, args=ocp.args.Composite(state=ocp.args.StandardSave(state),
                                                     meta=ocp.args.JsonSave(meta)), force=True)
        manager.wait_until_finished()
    return directory / str(cycle)


def latest_cycle(directory: str | os.PathLike) -> int | None:
    """The newest complete checkpoint's cycle number, or None if there is none."""
    directory = Path(directory)
    if not directory.is_dir():
        return None
    with _manager(directory, read_only=True) as manager:
        return manager.latest_step()


def abstract_state(config: Config, sharding: jax.sharding.Sharding | None = None) -> TrainState:
    """Shapes and dtypes of the :class:`TrainState` that ``config`` trains (no compute),
    placed by ``sharding`` (default: this process's first device)."""
    shapes = jax.eval_shape(make_train_for(config).init, jax.random.PRNGKey(0))
    sharding = sharding or jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
    return jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sharding), shapes)


def load_checkpoint(directory: str | os.PathLike, cycle: int | None = None,
                    expect: Config | None = None,
                    sharding: jax.sharding.Sharding | None = None) -> tuple[TrainState, Config]:
    """Restore ``(state, config)`` from ``directory`` (the newest cycle unless given).

    ``expect``: the config the caller is about to continue with (``--resume``); if
    its network or optimiser settings differ from the stored ones, a
    :class:`CheckpointError` names the differing fields.  ``sharding``: where the
    state goes (e.g. ``parallel.replicated(mesh)``; default: this process's first
    device).  A checkpoint restores on any device count, whatever wrote it.
    """
    directory = Path(directory)
    found = latest_cycle(directory)
    if found is None:
        raise CheckpointError(f"{directory}: no checkpoint found (train first with "
                              "`python -m lazyq_jax train --run-dir ...`)")
    cycle = found if cycle is None else cycle
    with _manager(directory, read_only=True) as manager:
        if cycle not in manager.all_steps():
            raise CheckpointError(f"{directory}: no checkpoint for cycle {cycle}; "
                                  f"available: {sorted(manager.all_steps())}")
        try:
            meta = manager.restore(cycle, args=ocp.args.Composite(meta=ocp.args.JsonRestore()))["meta"]
        except Exception as e:  # orbax raises many types for unreadable files
            raise CheckpointError(f"{directory / str(cycle)}: unreadable checkpoint metadata ({e})") from e
        if not isinstance(meta, dict) or meta.get("version") != CHECKPOINT_VERSION:
            version = meta.get("version") if isinstance(meta, dict) else None
            raise CheckpointError(f"{directory / str(cycle)}: checkpoint version {version!r}, this "
                                  f"lazyq-jax reads version {CHECKPOINT_VERSION}")
        try:
            config = from_dict(Config, meta["config"])
        except (ConfigError, KeyError, TypeError) as e:
            raise CheckpointError(f"{directory / str(cycle)}: stored config is not valid here ({e})") from e
        if expect is not None:
            _check_compatible(directory / str(cycle), config, expect)
        try:
            restored = manager.restore(cycle, args=ocp.args.Composite(
                state=ocp.args.StandardRestore(abstract_state(config, sharding))))
        except Exception as e:
            raise CheckpointError(f"{directory / str(cycle)}: partial or incompatible checkpoint "
                                  f"state ({type(e).__name__}: {e})") from e
    state = restored["state"]
    if int(state.cycle) != cycle:
        raise CheckpointError(f"{directory / str(cycle)}: holds cycle {int(state.cycle)}, expected {cycle}")
    return state.replace(key=jnp.asarray(state.key, jnp.uint32)), config


# Fields that change what a cycle computes (``cycles`` may grow: a run can be extended).
_MUST_MATCH = ("width", "depth", "learning_rate", "gamma", "double_dqn", "clip", "batch_size",
               "epochs", "resample_neighbours")


def _check_compatible(path: Path, stored: Config, expect: Config) -> None:
    diffs = [f"train.{name}: checkpoint {getattr(stored.train, name)!r} vs requested "
             f"{getattr(expect.train, name)!r}" for name in _MUST_MATCH
             if getattr(stored.train, name) != getattr(expect.train, name)]
    if stored.collect != expect.collect or stored.seed != expect.seed:
        diffs.append("collect config or seed differ (a different dataset)")
    if stored.neighbours != expect.neighbours:
        diffs.append("neighbours config differs")
    if diffs:
        raise CheckpointError(f"{path}: checkpoint does not match the requested config: "
                              + "; ".join(diffs))
