"""The main job, as library functions of ``(config, run_dir)``: collect, search, fit.

``run_dir`` holds ``config.json``, ``dataset.npz``, ``checkpoints/<cycle>/`` and
``metrics.jsonl`` (one JSON line per cycle).  The CLI is a thin layer over these.
"""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path

import jax
import numpy as np
from jax.sharding import Mesh
from tqdm.auto import tqdm

from lazyq_jax.checkpoint import CheckpointError, latest_cycle, load_latest_intact, save_checkpoint
from lazyq_jax.config import Config, to_dict
from lazyq_jax.data import DatasetError, collect, dataset_summary, load_dataset, save_dataset
from lazyq_jax.neighbours import build_index, search_all
from lazyq_jax.parallel import barrier, is_main_process, make_mesh, put, replicated, to_host
from lazyq_jax.train import check_mesh, make_train_for
from lazyq_jax.types import Transitions


# Tags that give every random purpose of a run its own key stream.  (fold_in is used
# rather than split: split(k, n)[i] == fold_in(k, i) with partitionable threefry, and
# the consumers fold in small counters of their own.)
_KEY_TAGS = {"collect": 0x636F6C6C, "neighbours": 0x6E656967, "train": 0x74726169,
             "resample": 0x72657361, "eval": 0x6576616C}


def purpose_key(seed: int, purpose: str) -> jax.Array:
    """The raw PRNG key of one purpose ('collect', 'neighbours', 'train', 'resample', 'eval')."""
    return jax.random.fold_in(jax.random.PRNGKey(seed), _KEY_TAGS[purpose])


def run_keys(config: Config) -> dict[str, jax.Array]:
    """Independent raw PRNG keys of a run, all derived from ``config.seed``."""
    return {name: purpose_key(config.seed, name) for name in ("collect", "neighbours", "train")}


def _log(msg: str) -> None:
    tqdm.write(msg)


def prepare_dataset(config: Config, run_dir: Path, progress: bool = True,
                    mesh: Mesh | None = None) -> Transitions:
    """``run_dir/dataset.npz`` if it was collected with this config and seed, else collect it
    (split over ``mesh``; only process 0 writes the file)."""
    path = run_dir / "dataset.npz"
    if path.exists():
        try:
            data, stored, seed = load_dataset(path)
            if stored == config.collect and seed == config.seed:
                _log(f"dataset: reusing {path} ({data.size:,} rows)")
                return data
            _log(f"dataset: {path} has another config or seed; collecting anew")
        except DatasetError as e:
            _log(f"dataset: ignoring unusable cache ({e}); collecting anew")
    t = time.perf_counter()
    data = collect(run_keys(config)["collect"], config.collect, mesh=mesh, progress=progress)
    summary = dataset_summary(data, config.collect.n_goals)
    if is_main_process():
        save_dataset(path, data, config.collect, seed=config.seed)
        (run_dir / "dataset_summary.json").write_text(json.dumps(summary, indent=1))
    _log(f"dataset: {data.size:,} rows, {summary['moves_that_moved_disk']} of {summary['moves']} "
         f"moves moved the disk ({time.perf_counter() - t:.1f} s) -> {path}")
    return data


def state_bounds(config: Config, s=None) -> tuple[float, float, float, float]:
    """``(x_min, y_min, x_max, y_max)`` of the grids over the push task's states.

    Finger starts lie in ``[-R, R]^2`` and every move adds ``action_length``, so states
    lie within ``R + (moves_per_start - 1) c`` (plus 1e-3); widened to cover ``s``
    (``[n, 2]``) if given.  Fixed bounds make the grid, hence the neighbour samples,
    the same for every dataset of a config (a study's seeds and their single runs).
    """
    c = config.collect
    r = c.start_range + (c.moves_per_start - 1) * c.push.action_length + 1e-3
    lo, hi = np.array([-r, -r]), np.array([r, r])
    if s is not None and len(s):
        s = np.asarray(s, np.float64)
        lo, hi = np.minimum(lo, s.min(axis=0)), np.maximum(hi, s.max(axis=0))
    return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])


def neighbours_for(config: Config, data: Transitions, cycle: int | None = None,
                   mesh: Mesh | None = None, *, n_valid: int | None = None,
                   bounds: tuple[float, float, float, float] | None = None) -> jax.Array:
    """``idx[N, k]``: each transition's neighbourhood (§V-A-2) with every row as a query.

    ``cycle`` picks a fresh random k-subset per cycle (``train.resample_neighbours``).
    ``mesh``: queries split over its devices (the same result for any device count).
    ``n_valid``: only the first ``n_valid`` rows are data, the rest padding (their
    rows of ``idx`` are 0); ``bounds``: the grid's bounds (default
    :func:`state_bounds`).  With the same bounds, a padded dataset gets the same
    neighbourhoods as unpadded.
    """
    key = run_keys(config)["neighbours"]
    if cycle is not None:
        key = jax.random.fold_in(purpose_key(config.seed, "resample"), cycle)
    nc = config.neighbours
    n = data.size if n_valid is None else int(n_valid)
    s, g = np.asarray(data.s[:n]), np.asarray(data.g[:n])
    index = build_index(s, g, k=nc.k, radius_s=nc.radius_s, radius_g=nc.radius_g,
                        growth=nc.growth, max_level=0, capacity=data.size,
                        bounds=bounds or state_bounds(config, s))
    return search_all(index, key, data.s, data.g, mesh=mesh, n_queries=n).idx


class RunDirError(ValueError):
    """The run directory holds another run that this call would overwrite."""


def mesh_for(config: Config) -> Mesh:
    """The device mesh of ``config.parallel``, with the config checked against it.

    Raises :class:`ConfigError` before anything compiles: more devices than exist,
    or a batch size the device count does not divide.
    """
    mesh = make_mesh(config.parallel)
    check_mesh(config.train, mesh)  # before the collection, not only when training starts
    return mesh


def fit(config: Config, run_dir: str | Path, *, resume: bool = False, overwrite: bool = False,
        progress: bool = True):
    """Collect (or reuse) the dataset, find neighbourhoods, train with a checkpoint per cycle.

    ``resume=True`` continues from the newest checkpoint in ``run_dir`` (or starts
    afresh if there is none) and ends with the same parameters as an uninterrupted
    run with the same config; a checkpoint of an incompatible config is refused
    before anything in ``run_dir`` is touched.  ``overwrite=True`` deletes existing
    checkpoints (it wins over ``resume``); with neither, they are refused.
    Every phase runs on the devices of ``config.parallel`` (:func:`mesh_for`).
    Returns ``(state, trainer, data)``.
    """
    mesh = mesh_for(config)
    run_dir = Path(run_dir)
    ckpt_dir = run_dir / "checkpoints"
    metrics_path = run_dir / "metrics.jsonl"
    restored = None
    if latest_cycle(ckpt_dir) is not None:
        if overwrite:  # wins over resume: `make train` always passes --resume
            if is_main_process():
                shutil.rmtree(ckpt_dir)
            barrier("overwrite")
        elif resume:
            try:  # refuses a mismatch early; skips (and keeps) damaged newest checkpoints
                found = load_latest_intact(ckpt_dir, expect=config, sharding=replicated(mesh),
                                           warn=_log)
            except CheckpointError as e:
                raise CheckpointError(f"{e}; to start this run afresh, pass --overwrite "
                                      "(make train ARGS=--overwrite)") from None
            restored = None if found is None else found[0]
            if found is None:
                _log(f"resume: no intact checkpoint left in {ckpt_dir}; starting afresh")
        else:
            raise RunDirError(f"{run_dir} already holds checkpoints of a run; continue it with "
                              "--resume, replace it with --overwrite, or pick another --run-dir")
    main = is_main_process()
    run_dir.mkdir(parents=True, exist_ok=True)
    if main:
        (run_dir / "config.json").write_text(json.dumps(to_dict(config), indent=1))
    _log(f"devices: {mesh.size} x {mesh.devices.flat[0].platform}"
         + (f" on {jax.process_count()} processes" if jax.process_count() > 1 else ""))
    timings: dict[str, float] = {}

    t = time.perf_counter()
    data = prepare_dataset(config, run_dir, progress, mesh)
    timings["dataset_s"] = time.perf_counter() - t

    t = time.perf_counter()
    first = 0 if restored is None else int(restored.cycle)
    idx = jax.block_until_ready(neighbours_for(
        config, data, first if config.train.resample_neighbours and first > 0 else None, mesh))
    timings["neighbours_s"] = time.perf_counter() - t
    _log(f"neighbours: {idx.shape[0]:,} queries x k={idx.shape[1]} ({timings['neighbours_s']:.1f} s)")

    tc = config.train
    bar = tqdm(total=tc.epochs, unit="epoch", disable=not progress, leave=False)
    trainer = make_train_for(config, progress=(lambda e: bar.update(1)) if progress else None,
                             mesh=mesh)
    data = put(data, replicated(mesh))
    if restored is not None:
        state = restored
        _log(f"resume: from cycle {int(state.cycle)} of {tc.cycles}")
        kept = [line for line in metrics_path.read_text().splitlines()
                if json.loads(line)["cycle"] <= int(state.cycle)] if metrics_path.exists() else []
        if main:
            metrics_path.write_text("".join(line + "\n" for line in kept))
    else:
        state = trainer.init(run_keys(config)["train"])
        if main:
            metrics_path.write_text("")
    state = put(state, replicated(mesh))

    run_cycle = jax.jit(trainer.run_cycle)
    t_train = time.perf_counter()
    while int(state.cycle) < tc.cycles:
        cycle = int(state.cycle)
        if tc.resample_neighbours and cycle > first:
            idx = neighbours_for(config, data, cycle, mesh)
        bar.reset()
        bar.set_description(f"cycle {cycle + 1}/{tc.cycles}")
        t = time.perf_counter()
        state, metrics = run_cycle(state, data, idx)
        metrics = to_host(metrics)
        seconds = time.perf_counter() - t
        save_checkpoint(ckpt_dir, state, config)
        record = {"cycle": int(state.cycle), "seconds": round(seconds, 2),
                  **{k: np.asarray(v).round(5).tolist() for k, v in metrics.items()}}
        if main:
            with metrics_path.open("a") as f:
                f.write(json.dumps(record) + "\n")
        _log(f"cycle {record['cycle']:>2}/{tc.cycles}: loss {record['loss']:.4f}  "
             f"Y {record['target_mean']:+.3f}±{record['target_std']:.3f}  "
             f"clip {record['clip_fraction']:.1%}  |β| {record['beta_norm_mean']:.2f}  "
             f"V(probes) {np.round(record['probe_values'], 2).tolist()}  ({seconds:.1f} s)")
    bar.close()
    timings["train_s"] = time.perf_counter() - t_train
    if main:
        (run_dir / "timings.json").write_text(json.dumps({k: round(v, 2) for k, v in timings.items()}))
    return state, trainer, data
