"""Orbax checkpoints of any training state (a pytree of arrays), with JSON beside them.

Layout: ``<directory>/<step>/{state, meta, checksums.json}``; ``meta`` is JSON holding
the checkpoint format version, the step and whatever the caller stores (the runner:
the run config, the method and the seeds whose states are stacked on a leading
axis).  Restores go against an abstract target (shapes and dtypes only, e.g.
``jax.eval_shape(agent.init, key, example)``) and land on this machine's default
device (or a given sharding), so a checkpoint written on a GPU reloads on a CPU
laptop.

``checksums.json`` holds the SHA-256 of every file orbax wrote: a truncated or
damaged checkpoint is recognised before orbax reads it (:class:`CheckpointDamaged`),
and :func:`load_latest_intact` then resumes from the newest intact one.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import json
import os
import shutil
from pathlib import Path
from typing import Any, Callable, Iterator

import jax
import orbax.checkpoint as ocp

CHECKPOINT_VERSION = 3  # 3: any agent's state, with the caller's metadata
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


def _save(manager: ocp.CheckpointManager, directory: Path, state: Any, step: int,
          meta: dict | None) -> Path:
    record = {**(meta or {}), "version": CHECKPOINT_VERSION, "step": int(step)}
    manager.save(int(step), args=ocp.args.Composite(state=ocp.args.StandardSave(state),
                                                     meta=ocp.args.JsonSave(record)), force=True)
    manager.wait_until_finished()
    step_dir = directory / str(int(step))
    if jax.process_index() == 0:
        (step_dir / CHECKSUMS).write_text(json.dumps(_digests(step_dir), indent=0))
    return step_dir


@contextlib.contextmanager
def checkpoint_writer(directory: str | os.PathLike) -> Iterator[Callable[..., Path]]:
    """``with checkpoint_writer(directory) as save: save(state, step, meta)`` for many saves
    into one directory (a training run's blocks): one orbax manager for all of them, each
    save synchronous and written with its checksums as :func:`save_checkpoint`'s.

    Opening a manager lists every checkpoint already there, so a manager per save costs
    time linear in the saves before it (docs/performance.md, "A checkpoint per block")."""
    directory = Path(directory)
    with _manager(directory) as manager:
        yield functools.partial(_save, manager, directory)


def save_checkpoint(directory: str | os.PathLike, state: Any, step: int, meta: dict | None = None
                    ) -> Path:
    """Save ``state`` as checkpoint number ``step`` under ``directory``, with ``meta`` (JSON)
    (for many saves into one directory, :func:`checkpoint_writer`)."""
    with checkpoint_writer(directory) as save:
        return save(state, step, meta)


def latest_step(directory: str | os.PathLike) -> int | None:
    """The newest complete checkpoint's step, or None if there is none."""
    directory = Path(directory)
    if not directory.is_dir():
        return None
    with _manager(directory, read_only=True) as manager:
        return manager.latest_step()


def all_steps(directory: str | os.PathLike) -> list[int]:
    """Steps of all complete checkpoints under ``directory``, oldest first."""
    directory = Path(directory)
    if not directory.is_dir():
        return []
    with _manager(directory, read_only=True) as manager:
        return sorted(manager.all_steps())


def _read_meta(manager, path: Path) -> dict:
    try:
        meta = manager.restore(int(path.name), args=ocp.args.Composite(meta=ocp.args.JsonRestore()))["meta"]
    except Exception as e:  # orbax raises many types for unreadable files
        raise CheckpointDamaged(f"{path}: unreadable checkpoint metadata ({type(e).__name__})") from e
    if not isinstance(meta, dict) or meta.get("version") != CHECKPOINT_VERSION:
        version = meta.get("version") if isinstance(meta, dict) else None
        raise CheckpointError(f"{path}: checkpoint version {version!r}, this lazyq-jax reads "
                              f"version {CHECKPOINT_VERSION}; train it again (--overwrite)")
    return meta


def read_meta(directory: str | os.PathLike, step: int | None = None) -> dict:
    """The JSON stored with checkpoint ``step`` (default: the newest) under ``directory``."""
    directory = Path(directory)
    step = latest_step(directory) if step is None else step
    if step is None:
        raise CheckpointError(f"{directory}: no checkpoint found")
    with _manager(directory, read_only=True) as manager:
        return _read_meta(manager, directory / str(step))


def load_checkpoint(directory: str | os.PathLike, target: Any, step: int | None = None,
                    sharding: jax.sharding.Sharding | None = None,
                    check: Callable[[Path, dict], None] | None = None) -> tuple[Any, dict]:
    """Restore ``(state, meta)`` from ``directory`` (the newest step unless given).

    ``target``: the abstract state to restore into (shapes and dtypes, e.g.
    ``jax.eval_shape(agent.init, key, example)``), placed by ``sharding`` (default:
    this process's first device); a checkpoint restores on any device count, whatever
    wrote it.  ``check(path, meta)`` may raise :class:`CheckpointError` for a checkpoint
    that does not fit what the caller is about to do (before the state is read).  A
    damaged or truncated checkpoint raises :class:`CheckpointDamaged` (see
    :func:`load_latest_intact`).
    """
    directory = Path(directory)
    found = latest_step(directory)
    if found is None:
        raise CheckpointError(f"{directory}: no checkpoint found (train first)")
    step = found if step is None else step
    path = directory / str(step)
    with _manager(directory, read_only=True) as manager:
        if step not in manager.all_steps():
            raise CheckpointError(f"{directory}: no checkpoint for step {step}; "
                                  f"available: {sorted(manager.all_steps())}")
        _verify(path)
        meta = _read_meta(manager, path)
        if check is not None:
            check(path, meta)
        place = sharding or jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
        target = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=place), target)
        try:
            restored = manager.restore(step, args=ocp.args.Composite(
                state=ocp.args.StandardRestore(target)))
        except Exception as e:
            first = str(e).strip().splitlines()[0][:300] if str(e).strip() else ""
            raise CheckpointDamaged(f"{path}: partial, damaged or incompatible checkpoint state "
                                    f"({type(e).__name__}: {first})") from None
    return restored["state"], meta


def load_latest_intact(directory: str | os.PathLike, target: Any,
                       sharding: jax.sharding.Sharding | None = None, *,
                       check: Callable[[Path, dict], None] | None = None,
                       warn: Callable[[str], None] = print) -> tuple[Any, dict] | None:
    """The newest checkpoint under ``directory`` that is intact, for ``--resume``.

    Newer checkpoints that are damaged or truncated are moved aside to
    ``<directory>_damaged/<step>`` (nothing is deleted) with a warning through
    ``warn``, and the next older one is tried.  A checkpoint that ``check`` refuses is
    an error (older ones would not fit either).  Returns None when no intact
    checkpoint is left.
    """
    directory = Path(directory)
    for step in reversed(all_steps(directory)):
        try:
            return load_checkpoint(directory, target, step, sharding=sharding, check=check)
        except CheckpointDamaged as e:
            aside = directory.parent / f"{directory.name}_damaged" / str(step)
            if jax.process_index() == 0:
                aside.parent.mkdir(parents=True, exist_ok=True)
                if aside.exists():
                    shutil.rmtree(aside)
                shutil.move(str(directory / str(step)), str(aside))
            warn(f"warning: {e}; moved it to {aside} and resuming from an older checkpoint")
    return None
