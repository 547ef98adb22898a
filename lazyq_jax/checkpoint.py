"""Per-cycle orbax checkpoints of a :class:`TrainState`, with the run config beside them.

Layout: ``<run_dir>/checkpoints/<cycle>/{state, meta, checksums.json}``; ``meta`` is JSON
holding the checkpoint format version, the full :class:`Config` and, for a study's
checkpoint of several seeds trained together (every leaf stacked on a leading seed
axis), the seeds.  Restores go against an abstract target built from that config
(shapes and dtypes only) and land on this machine's default device, so a checkpoint
written on a GPU reloads on a CPU laptop.

``checksums.json`` holds the SHA-256 of every file orbax wrote: a truncated or
damaged checkpoint is recognised before orbax reads it (:class:`CheckpointDamaged`),
and :func:`load_latest_intact` then resumes from the newest intact one.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from pathlib import Path
from typing import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp

from lazyq_jax.config import Config, ConfigError, from_dict, to_dict
from lazyq_jax.train import TrainState, make_train_for

CHECKPOINT_VERSION = 2  # 2: hidden Dense layers without bias
CHECKSUMS = "checksums.json"


class CheckpointError(ValueError):
    """A checkpoint is missing, partial, or does not fit the requested config."""


class CheckpointDamaged(CheckpointError):
    """A checkpoint's files are truncated, damaged or missing (older ones may be intact)."""


def _manager(directory: Path, read_only: bool = False) -> ocp.CheckpointManager:
    # (orbax's read_only mode logs warnings on every open; create=False is enough.)
    options = ocp.CheckpointManagerOptions(max_to_keep=None, create=not read_only,
                                           enable_async_checkpointing=False)
    return ocp.CheckpointManager(directory.absolute(), options=options, item_names=("state", "meta"))


def _digests(step_dir: Path) -> dict[str, str]:
    files = sorted(p for p in step_dir.rglob("*") if p.is_file() and p.name != CHECKSUMS)
    return {str(p.relative_to(step_dir)): hashlib.sha256(p.read_bytes()).hexdigest() for p in files}


def _verify(step_dir: Path) -> None:
    """Raise :class:`CheckpointDamaged` naming the first file whose contents changed."""
    path = step_dir / CHECKSUMS
    if not path.exists():  # written by an older lazyq-jax: orbax's own checks only
        return
    try:
        expected = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise CheckpointDamaged(f"{step_dir}: unreadable {CHECKSUMS} ({e})") from e
    found = _digests(step_dir)
    for name, digest in expected.items():
        if name not in found:
            raise CheckpointDamaged(f"{step_dir}: file {name} is missing")
        if found[name] != digest:
            raise CheckpointDamaged(f"{step_dir}: file {name} is damaged or truncated "
                                    "(its checksum differs from the one written with it)")


def _step(state: TrainState) -> int:
    cycles = np.unique(np.asarray(state.cycle))
    if cycles.size != 1:
        raise ValueError(f"stacked states must all be at the same cycle, got {cycles.tolist()}")
    return int(cycles[0])


def save_checkpoint(directory: str | os.PathLike, state: TrainState, config: Config, *,
                    seeds: Sequence[int] | None = None) -> Path:
    """Save ``state`` as checkpoint number ``state.cycle`` under ``directory``.

    ``seeds``: ``state`` holds these seeds' states stacked on a leading axis (a study);
    all must be at the same cycle.
    """
    directory = Path(directory)
    cycle = _step(state)
    meta = {"version": CHECKPOINT_VERSION, "cycle": cycle, "config": to_dict(config)}
    if seeds is not None:
        meta["seeds"] = [int(s) for s in seeds]
    with _manager(directory) as manager:
        manager.save(cycle, args=ocp.args.Composite(state=ocp.args.StandardSave(state),
                                                     meta=ocp.args.JsonSave(meta)), force=True)
        manager.wait_until_finished()
    step_dir = directory / str(cycle)
    if jax.process_index() == 0:
        (step_dir / CHECKSUMS).write_text(json.dumps(_digests(step_dir), indent=0))
    return step_dir


def latest_cycle(directory: str | os.PathLike) -> int | None:
    """The newest complete checkpoint's cycle number, or None if there is none."""
    directory = Path(directory)
    if not directory.is_dir():
        return None
    with _manager(directory, read_only=True) as manager:
        return manager.latest_step()


def all_cycles(directory: str | os.PathLike) -> list[int]:
    """Cycle numbers of all complete checkpoints under ``directory``, oldest first."""
    directory = Path(directory)
    if not directory.is_dir():
        return []
    with _manager(directory, read_only=True) as manager:
        return sorted(manager.all_steps())


def abstract_state(config: Config, sharding: jax.sharding.Sharding | None = None,
                   seeds: int | None = None) -> TrainState:
    """Shapes and dtypes of the :class:`TrainState` that ``config`` trains (no compute),
    placed by ``sharding`` (default: this process's first device); with ``seeds``, that
    many states stacked on a leading axis."""
    init = make_train_for(config).init
    keys = jax.random.PRNGKey(0) if seeds is None else jnp.zeros((seeds, 2), jnp.uint32)
    shapes = jax.eval_shape(init if seeds is None else jax.vmap(init), keys)
    sharding = sharding or jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
    return jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sharding), shapes)


def _read_meta(manager, path: Path) -> dict:
    try:
        meta = manager.restore(int(path.name), args=ocp.args.Composite(meta=ocp.args.JsonRestore()))["meta"]
    except Exception as e:  # orbax raises many types for unreadable files
        raise CheckpointDamaged(f"{path}: unreadable checkpoint metadata ({type(e).__name__})") from e
    if not isinstance(meta, dict) or meta.get("version") != CHECKPOINT_VERSION:
        version = meta.get("version") if isinstance(meta, dict) else None
        raise CheckpointError(f"{path}: checkpoint version {version!r}, this lazyq-jax reads "
                              f"version {CHECKPOINT_VERSION}")
    return meta


def load_checkpoint(directory: str | os.PathLike, cycle: int | None = None,
                    expect: Config | None = None,
                    sharding: jax.sharding.Sharding | None = None, *,
                    seeds: Sequence[int] | None = None,
                    target: TrainState | None = None) -> tuple[TrainState, Config]:
    """Restore ``(state, config)`` from ``directory`` (the newest cycle unless given).

    ``expect``: the config the caller is about to continue with (``--resume``); if
    its network or optimiser settings differ from the stored ones, a
    :class:`CheckpointError` names the differing fields.  ``seeds``: the checkpoint
    must hold exactly these seeds stacked (a study); without it, a single run's.
    ``sharding``: where the state goes (e.g. ``parallel.replicated(mesh)``; default:
    this process's first device).  A checkpoint restores on any device count,
    whatever wrote it.  A damaged or truncated checkpoint raises
    :class:`CheckpointDamaged` (see :func:`load_latest_intact`).  ``target``: the
    abstract state to restore into (e.g. ``jax.eval_shape(trainer.init, key)`` of a
    task with another network input than the push task's; default
    :func:`abstract_state` of the stored config), placed by ``sharding``.
    """
    directory = Path(directory)
    found = latest_cycle(directory)
    if found is None:
        raise CheckpointError(f"{directory}: no checkpoint found (train first with "
                              "`python -m lazyq_jax train --run-dir ...`)")
    cycle = found if cycle is None else cycle
    path = directory / str(cycle)
    with _manager(directory, read_only=True) as manager:
        if cycle not in manager.all_steps():
            raise CheckpointError(f"{directory}: no checkpoint for cycle {cycle}; "
                                  f"available: {sorted(manager.all_steps())}")
        _verify(path)
        meta = _read_meta(manager, path)
        try:
            config = from_dict(Config, meta["config"])
        except (ConfigError, KeyError, TypeError) as e:
            raise CheckpointError(f"{path}: stored config is not valid here ({e})") from e
        stored_seeds = meta.get("seeds")
        wanted = None if seeds is None else [int(s) for s in seeds]
        if stored_seeds != wanted:
            what = lambda s: "a single run" if s is None else f"a study of seeds {s}"
            raise CheckpointError(f"{path}: holds {what(stored_seeds)}, expected {what(wanted)}")
        if expect is not None:
            _check_compatible(path, config, expect)
        if target is None:
            target = abstract_state(config, sharding, None if seeds is None else len(seeds))
        else:
            place = sharding or jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
            target = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=place),
                                  target)
        try:
            restored = manager.restore(cycle, args=ocp.args.Composite(
                state=ocp.args.StandardRestore(target)))
        except Exception as e:
            first = str(e).strip().splitlines()[0][:300] if str(e).strip() else ""
            raise CheckpointDamaged(f"{path}: partial, damaged or incompatible checkpoint state "
                                    f"({type(e).__name__}: {first})") from None
    state = restored["state"]
    if _step(state) != cycle:
        raise CheckpointError(f"{path}: holds cycle {_step(state)}, expected {cycle}")
    return state.replace(key=jnp.asarray(state.key, jnp.uint32)), config


def load_latest_intact(directory: str | os.PathLike, expect: Config,
                       sharding: jax.sharding.Sharding | None = None, *,
                       seeds: Sequence[int] | None = None, target: TrainState | None = None,
                       warn: Callable[[str], None] = print) -> tuple[TrainState, Config] | None:
    """The newest checkpoint under ``directory`` that is intact, for ``--resume``.

    Newer checkpoints that are damaged or truncated are moved aside to
    ``<directory>_damaged/<cycle>`` (nothing is deleted) with a warning through
    ``warn``, and the next older one is tried.  A checkpoint that does not fit
    ``expect`` is an error (older ones would not fit either).  Returns None when
    no intact checkpoint is left.  ``target``: as for :func:`load_checkpoint`.
    """
    directory = Path(directory)
    for cycle in reversed(all_cycles(directory)):
        try:
            return load_checkpoint(directory, cycle, expect=expect, sharding=sharding, seeds=seeds,
                                   target=target)
        except CheckpointDamaged as e:
            aside = directory.parent / f"{directory.name}_damaged" / str(cycle)
            if jax.process_index() == 0:
                aside.parent.mkdir(parents=True, exist_ok=True)
                if aside.exists():
                    shutil.rmtree(aside)
                shutil.move(str(directory / str(cycle)), str(aside))
            warn(f"warning: {e}; moved it to {aside} and resuming from an older checkpoint")
    return None


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
    if stored.online != expect.online:
        diffs.append("online config differs (another sequence of datasets)")
    if diffs:
        raise CheckpointError(f"{path}: checkpoint does not match the requested config: "
                              + "; ".join(diffs))
