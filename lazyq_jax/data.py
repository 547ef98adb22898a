"""Off-policy data collection (paper §V-A-3) and versioned dataset files."""

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

from lazyq_jax.config import CollectConfig, ConfigError, PushConfig, from_dict, to_dict
from lazyq_jax.env import PushEnv, disk_moved, push_reward, sample_outside_disk
from lazyq_jax.parallel import AXIS, mesh_size, put, sharded, to_host
from lazyq_jax.types import Transitions

DATASET_FORMAT = "lazyq-jax-dataset"
DATASET_VERSION = 1
# Per-row shapes; "d_s" / "n_a" stand for the stored state and action sizes (meta
# "state_dim" / "action_dim"; 2 for files that predate them: the push task's).
_FIELDS = {"s": (np.float32, ("d_s",)), "a": (np.float32, ("n_a",)), "s_next": (np.float32, ("d_s",)),
           "r": (np.float32, ()), "g": (np.float32, ()), "done": (np.bool_, ())}


class DatasetError(ValueError):
    """A dataset file is missing, truncated, foreign, or of another version."""


def make_episode_fn(env: PushEnv, config: CollectConfig):
    """``episode(key) -> dict`` of one random episode, unbatched (vmap it).

    The finger starts uniform in ``[-R, R]^2`` outside the disk (at the origin) and
    makes ``moves_per_start`` moves in one uniformly random direction; each move is
    labelled with ``n_goals`` fresh goals uniform in ``[-pi, pi)``.
    """
    pc = env.config

    def episode(key):
        k_start, k_dir, k_goal = jax.random.split(key, 3)
        start = sample_outside_disk(k_start, jnp.zeros(2), config.start_range, pc.contact_distance)
        phi = jax.random.uniform(k_dir, (), jnp.float32, -jnp.pi, jnp.pi)
        action = pc.action_length * jnp.stack([jnp.cos(phi), jnp.sin(phi)])
        return repeated_moves(env.step, env.reset(start), action, k_goal, config, pc,
                              observe=lambda st: st.relative)

    return episode


def repeated_moves(step, state, action, key, config: CollectConfig, push: PushConfig, observe):
    """One §V-A-3 episode from ``state``: ``config.moves_per_start`` moves with ``action``
    (``step(state, action) -> (state, disk_delta)``), each labelled with
    ``config.n_goals`` goals uniform in ``[-pi, pi)`` and Eq. (15)'s rewards;
    ``observe(state)`` is the agent's state ``s``.  Returns the episode's dict (leaves
    ``[T, ...]``) for :func:`episodes_to_transitions`."""
    goals = jax.random.uniform(key, (config.moves_per_start, config.n_goals), jnp.float32,
                               -jnp.pi, jnp.pi)

    def move(state, _):
        nxt, delta = step(state, action)
        return nxt, (observe(state), observe(nxt), delta)

    _, (s, s_next, delta) = jax.lax.scan(move, state, None, length=config.moves_per_start)
    reward = push_reward(delta[:, None, :], goals, move_threshold=push.move_threshold,
                         cos_threshold=push.cos_threshold)
    return {"s": s, "a": jnp.broadcast_to(action, s.shape[:1] + action.shape), "s_next": s_next,
            "delta": delta,
            "g": goals, "r": reward, "moved": disk_moved(delta, push.move_threshold)}


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
    as NumPy.  The task's collectors (:func:`collect`, the arm's) are built on it."""
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


def collect(key: jax.Array, config: CollectConfig = CollectConfig(), *, mesh: Mesh | None = None,
            progress: bool = True) -> Transitions:
    """Simulate the random pushes of §V-A-3 in jitted MJX batches and relabel for many goals.

    Returns ``Transitions`` with ``n_goals`` rows per simulated move, push-major
    (row ``= move * n_goals + goal``).  ``s`` is the finger position relative to the disk.

    Episodes end at a push that moves the disk (``|delta| >= move_threshold``, which
    gives reward +-1 for every goal): that push is a terminal transition
    (``done=True``), and the episode's later moves are never part of the dataset
    (the paper resets the disk).  So ``N <= n_starts * moves_per_start * n_goals``;
    with the paper's 5000 x 2 x 100 that is at most 1,000,000 rows.

    ``mesh`` (see :mod:`lazyq_jax.parallel`): the chunks of ``chunk_size`` episodes are
    spread over its devices with ``shard_map``, one chunk per device and call; with
    several processes each simulates the chunks of its own devices and all receive
    the whole dataset.

    Same ``key`` and config give the bitwise same dataset on any number of devices:
    every device runs the same program on a chunk of the same size, which holds the
    same episodes.  (Another ``chunk_size`` can change the last bits of a few
    episodes: XLA's vectorised code depends on the batch size.)  The physics runs in
    float64 when ``config.push.float64`` (see :class:`PushConfig`).
    """
    if not isinstance(config, CollectConfig):
        raise TypeError(f"collect needs a CollectConfig, got {type(config).__name__}")
    make = lambda: make_episode_fn(PushEnv(config.push), config)
    eps = run_episodes(key, make, config, config.n_starts, config.chunk_size,
                       float64=config.push.float64, mesh=mesh, progress=progress)
    return episodes_to_transitions(eps, config.n_goals)


def episodes_to_transitions(eps: dict, n_goals: int) -> Transitions:
    """Transitions of episodes (leaves ``[E, T, ...]``: ``s, a, s_next, delta, g, r, moved``),
    each move relabelled for its ``n_goals`` goals, moves after one that moved the disk
    dropped (the episode ended there)."""
    delta = eps["delta"]  # [E, T, 2]
    if not np.all(np.isfinite(delta)):
        bad = int(np.sum(~np.all(np.isfinite(delta), axis=-1)))
        raise FloatingPointError(f"collect: the physics returned non-finite disk positions for "
                                 f"{bad} pushes; check the PushConfig solver settings")
    moved = eps["moved"]  # [E, T], the same test that made the rewards nonzero
    # A move exists if no earlier move of its episode moved the disk.
    ended_before = np.cumsum(moved, axis=1) - moved > 0
    keep = ~ended_before  # [E, T]
    per_move = lambda x: np.repeat(x[keep], n_goals, axis=0)
    return Transitions(
        s=jnp.asarray(per_move(eps["s"]), jnp.float32),
        a=jnp.asarray(per_move(eps["a"]), jnp.float32),
        s_next=jnp.asarray(per_move(eps["s_next"]), jnp.float32),
        r=jnp.asarray(eps["r"][keep].reshape(-1), jnp.float32),
        g=jnp.asarray(eps["g"][keep].reshape(-1), jnp.float32),
        done=jnp.asarray(per_move(moved), bool),
    )


def dataset_summary(data: Transitions, n_goals: int) -> dict:
    """Counts the README reports: moves, moves that moved the disk, rewards per goal octant.

    Octant ``i`` holds the goals within 22.5 degrees of ``45 * i`` degrees: octants
    0, 2, 4, 6 are centred on the axes (0, 90, 180, 270), the others on diagonals.
    """
    r = np.asarray(data.r)
    octant = np.round(np.asarray(data.g) / (np.pi / 4)).astype(int) % 8
    per = []
    for i in range(8):
        m = octant == i
        per.append({"centre_deg": 45 * i, "positive": int(np.sum(r[m] > 0)),
                    "negative": int(np.sum(r[m] < 0)), "zero": int(np.sum(r[m] == 0))})
    return {"rows": int(r.size), "moves": int(r.size // n_goals),
            "moves_that_moved_disk": int(np.asarray(data.done).sum() // n_goals),
            "reward_by_goal_octant": per}


def save_dataset(path: str | os.PathLike, data: Transitions, config: CollectConfig,
                 seed: int | None = None) -> Path:
    """Write ``data`` with its config and seed to a versioned ``.npz`` (no pickle).

    The write goes to a temporary file first and is renamed into place, so an
    interrupted save never leaves a half-written dataset under ``path``.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    meta = {"format": DATASET_FORMAT, "version": DATASET_VERSION, "config": to_dict(config),
            "seed": seed, "rows": data.size, "state_dim": int(data.s.shape[1]),
            "action_dim": int(data.a.shape[1])}
    arrays = {name: np.asarray(getattr(data, name)) for name in _FIELDS}
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        np.savez(f, meta=np.frombuffer(json.dumps(meta).encode(), np.uint8), **arrays)
    os.replace(tmp, path)
    return path


def load_dataset(path: str | os.PathLike) -> tuple[Transitions, CollectConfig, int | None]:
    """Read a file written by :func:`save_dataset`: ``(data, config, seed)``.

    Raises :class:`DatasetError` naming the file for a missing, truncated, foreign
    or other-version file, or one whose arrays have wrong shapes or dtypes.
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: no such dataset file")
    try:
        with np.load(path, allow_pickle=False) as z:
            if "meta" not in z.files:
                raise DatasetError(f"{path}: not a lazyq-jax dataset (no 'meta' entry)")
            meta = json.loads(z["meta"].tobytes().decode())
            arrays = {name: z[name] for name in _FIELDS if name in z.files}
    except DatasetError:
        raise
    except (zipfile.BadZipFile, OSError, EOFError, ValueError, KeyError, UnicodeDecodeError) as e:
        raise DatasetError(f"{path}: unreadable or truncated dataset file ({e})") from e
    if not isinstance(meta, dict) or meta.get("format") != DATASET_FORMAT:
        raise DatasetError(f"{path}: not a lazyq-jax dataset (format {meta.get('format')!r})"
                           if isinstance(meta, dict) else f"{path}: not a lazyq-jax dataset")
    if meta.get("version") != DATASET_VERSION:
        raise DatasetError(f"{path}: dataset version {meta.get('version')} but this lazyq-jax "
                           f"reads version {DATASET_VERSION}; re-collect it")
    rows = meta.get("rows")
    sizes = {"d_s": meta.get("state_dim", 2), "n_a": meta.get("action_dim", 2)}
    for name, (dtype, tail) in _FIELDS.items():
        tail = tuple(sizes.get(t, t) for t in tail)
        if name not in arrays:
            raise DatasetError(f"{path}: array {name!r} is missing")
        arr = arrays[name]
        if arr.dtype != dtype or arr.shape != (rows, *tail):
            raise DatasetError(f"{path}: array {name!r} has {arr.dtype}{list(arr.shape)}, "
                               f"expected {np.dtype(dtype)}{[rows, *tail]}")
    try:
        config = from_dict(CollectConfig, meta["config"])
    except (ConfigError, TypeError, KeyError) as e:
        raise DatasetError(f"{path}: its stored config is not valid here ({e})") from e
    data = Transitions(**{k: jnp.asarray(v) for k, v in arrays.items()})
    return data, config, meta.get("seed")
