"""Datasets: batched episode collection, relabelled transitions, versioned files.

The tasks build their collectors on :func:`run_episodes` (jitted batches of an
unbatched ``episode(key) -> dict``, split over a device mesh) and
:func:`episodes_to_transitions` (one row per move and goal; an episode ends at its
first terminal move).  :func:`save_dataset` / :func:`load_dataset` keep any
:class:`~lazyq_jax.types.Transitions` with a JSON header (what made it) in an
``.npz`` file: no pickle.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import zipfile
from pathlib import Path
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, PartitionSpec as P
from tqdm.auto import tqdm

from lazyq_jax.parallel import AXIS, mesh_size, put, sharded, to_host
from lazyq_jax.types import Transitions

DATASET_FORMAT = "lazyq-jax-dataset"
DATASET_VERSION = 2  # 2: vector and absent goals; the header names what made the data


class DatasetError(ValueError):
    """A dataset file is missing, truncated, foreign, or of another version."""


# ----------------------------------------------------------------------------- collection


def _precision(float64: bool):
    """``jax.enable_x64(True)`` for float64 physics; the caller's precision otherwise."""
    return jax.enable_x64(True) if float64 else contextlib.nullcontext()


def _episode_keys(key: jax.Array, first: int, count: int) -> jax.Array:
    # fold_in by global episode index: the dataset does not depend on the chunking.
    return jax.vmap(lambda i: jax.random.fold_in(key, i))(jnp.arange(first, first + count))


_COLLECTORS: dict = {}


def _collector(cache_key, make_episode: Callable, mesh: Mesh | None):
    """The jitted batch of episodes, kept per ``cache_key`` (a hashable config) and mesh so
    that collecting again does not recompile."""
    if (cache_key, mesh) not in _COLLECTORS:
        episodes = jax.vmap(make_episode())
        if mesh is not None:  # no collectives: each device simulates its own chunk
            episodes = jax.shard_map(episodes, mesh=mesh, in_specs=P(AXIS), out_specs=P(AXIS),
                                     check_vma=False)
        if len(_COLLECTORS) >= 8:
            _COLLECTORS.pop(next(iter(_COLLECTORS)))
        _COLLECTORS[(cache_key, mesh)] = jax.jit(episodes)
    return _COLLECTORS[(cache_key, mesh)]


def run_episodes(key: jax.Array, make_episode: Callable, cache_key, n: int, chunk_size: int, *,
                 float64: bool, mesh: Mesh | None = None, progress: bool = True,
                 desc: str = "collect (episodes)") -> dict:
    """``n`` episodes of ``make_episode()`` (an unbatched ``episode(key) -> dict``) in jitted
    batches of equal chunks of at most ``chunk_size``, one chunk per device and call;
    episode ``i`` gets ``fold_in(key, i)``.  Returns the dict with leaves ``[n, ...]``
    as NumPy.

    The same ``key`` gives bitwise the same episodes on any number of devices: every
    device runs the same program on a chunk of the same size.  (Another ``chunk_size``
    can change the last bits of a few episodes: XLA's vectorised code depends on the
    batch size.)"""
    d = mesh_size(mesh)
    chunk = math.ceil(n / math.ceil(n / chunk_size))  # equal chunks, little padding
    n_calls = math.ceil(math.ceil(n / chunk) / d)
    per_call = d * chunk
    parts = []
    bar = tqdm(total=n, desc=desc, unit="ep", disable=not progress, leave=False)
    with _precision(float64):
        run = _collector(cache_key, make_episode, mesh)
        for c in range(n_calls):
            keys = put(_episode_keys(key, c * per_call, per_call), sharded(mesh))
            out = to_host(run(keys))
            take = min(per_call, n - c * per_call)
            parts.append({k: v[:take] for k, v in out.items()})
            bar.update(take)
    bar.close()
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def episodes_to_transitions(eps: dict, n_goals: int) -> Transitions:
    """Transitions of episodes (leaves ``[E, T, ...]``: ``s, a, s_next, moved`` per move;
    ``g, r: [E, T, n_goals]``, each move relabelled for its ``n_goals`` goals), one row
    per move and goal (move-major), the moves after a terminal one (``moved``) dropped:
    the episode ended there.  Non-finite next states (broken physics) raise."""
    s_next = eps["s_next"]
    if not np.all(np.isfinite(s_next)):
        bad = int(np.sum(~np.all(np.isfinite(s_next.reshape(*s_next.shape[:2], -1)), axis=-1)))
        raise FloatingPointError(f"collect: the physics returned non-finite states for {bad} "
                                 "moves; check the task's solver settings")
    moved = eps["moved"]  # [E, T]
    # A move exists if no earlier move of its episode ended it.
    keep = ~(np.cumsum(moved, axis=1) - moved > 0)  # [E, T]
    per_move = lambda x: np.repeat(x[keep], n_goals, axis=0)
    g = eps["g"][keep]
    return Transitions(
        s=jnp.asarray(per_move(eps["s"]), jnp.float32),
        a=jnp.asarray(per_move(eps["a"]), jnp.float32),
        s_next=jnp.asarray(per_move(s_next), jnp.float32),
        r=jnp.asarray(eps["r"][keep].reshape(-1), jnp.float32),
        g=jnp.asarray(g.reshape(-1, *g.shape[2:]), jnp.float32),
        done=jnp.asarray(per_move(moved), bool),
    )


# ----------------------------------------------------------------------------- files


def save_dataset(path: str | os.PathLike, data: Transitions, meta: dict | None = None) -> Path:
    """Write ``data`` with ``meta`` (JSON: what made it, e.g. the task, its collect
    config and the seed) to a versioned ``.npz`` (no pickle).

    The write goes to a temporary file first and is renamed into place, so an
    interrupted save never leaves a half-written dataset under ``path``.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    header = {"format": DATASET_FORMAT, "version": DATASET_VERSION, "rows": data.size,
              "goal": "none" if data.g is None else ("angle" if np.ndim(data.g) == 1 else "vector"),
              "meta": meta or {}}
    arrays = {name: np.asarray(getattr(data, name)) for name in ("s", "a", "s_next", "r", "done")}
    if data.g is not None:
        arrays["g"] = np.asarray(data.g)
    if data.traj_last is not None:
        arrays["traj_last"] = np.asarray(data.traj_last, np.int32)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        np.savez(f, header=np.frombuffer(json.dumps(header).encode(), np.uint8), **arrays)
    os.replace(tmp, path)
    return path


def load_dataset(path: str | os.PathLike) -> tuple[Transitions, dict]:
    """Read a file written by :func:`save_dataset`: ``(data, meta)``.

    Raises :class:`DatasetError` naming the file for a missing, truncated, foreign
    or other-version file, or one whose arrays have wrong shapes or dtypes.
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: no such dataset file")
    try:
        with np.load(path, allow_pickle=False) as z:
            if "header" not in z.files:
                old = "meta" in z.files  # version 1 kept its header under "meta"
                raise DatasetError(f"{path}: " + ("a dataset of an older lazyq-jax (version 1); "
                                                  "collect it again" if old else
                                                  "not a lazyq-jax dataset (no header)"))
            header = json.loads(z["header"].tobytes().decode())
            arrays = {name: z[name] for name in z.files if name != "header"}
    except DatasetError:
        raise
    except (zipfile.BadZipFile, OSError, EOFError, ValueError, KeyError, UnicodeDecodeError) as e:
        raise DatasetError(f"{path}: unreadable or truncated dataset file ({e})") from e
    if not isinstance(header, dict) or header.get("format") != DATASET_FORMAT:
        raise DatasetError(f"{path}: not a lazyq-jax dataset")
    if header.get("version") != DATASET_VERSION:
        raise DatasetError(f"{path}: dataset version {header.get('version')} but this lazyq-jax "
                           f"reads version {DATASET_VERSION}; collect it again")
    rows, goal = header.get("rows"), header.get("goal")
    names = ("s", "a", "s_next", "r", "done") + (() if goal == "none" else ("g",))
    for name in names:
        if name not in arrays:
            raise DatasetError(f"{path}: array {name!r} is missing")
    expect = {"s": (np.float32, 2), "a": (np.float32, 2), "s_next": (np.float32, 2),
              "r": (np.float32, 1), "done": (np.bool_, 1), "g": (np.float32, 1 if goal == "angle" else 2)}
    for name in names:
        dtype, ndim = expect[name]
        arr = arrays[name]
        if arr.dtype != dtype or arr.ndim != ndim or arr.shape[0] != rows:
            raise DatasetError(f"{path}: array {name!r} has {arr.dtype}{list(arr.shape)}, expected "
                               f"{np.dtype(dtype)} with {ndim} dimension(s) and {rows} rows")
    if arrays["s_next"].shape != arrays["s"].shape:
        raise DatasetError(f"{path}: s_next {arrays['s_next'].shape} does not match s {arrays['s'].shape}")
    last = arrays.get("traj_last")
    if last is not None and (last.dtype != np.int32 or last.shape != (rows,)
                             or (rows and (last.min() < 0 or last.max() >= rows))):
        raise DatasetError(f"{path}: array 'traj_last' has {last.dtype}{list(last.shape)}, expected "
                           f"int32 [{rows}] of row indices")
    data = Transitions(s=jnp.asarray(arrays["s"]), a=jnp.asarray(arrays["a"]),
                       s_next=jnp.asarray(arrays["s_next"]), r=jnp.asarray(arrays["r"]),
                       g=None if goal == "none" else jnp.asarray(arrays["g"]),
                       done=jnp.asarray(arrays["done"]),
                       traj_last=None if last is None else jnp.asarray(last))
    return data, header.get("meta", {})
