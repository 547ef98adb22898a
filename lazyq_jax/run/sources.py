"""Where a run's data come from: the task's static dataset of every seed, and online rounds
that grow it with the agent's own episodes.

Both give the runner the seeds' datasets padded to one length and stacked
(:class:`SeedData`), so that every phase is one program over all seeds.  The online
source pads to the capacity of the whole run halved as often as the data allow
(:meth:`OnlineRounds.size_for`), and doubles it when a round outgrows it: a run compiles
its programs for at most a few shapes, and the early rounds do not pay for the rows the
later ones will add.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh
from tqdm.auto import tqdm

from lazyq_jax.config import Config, ConfigError, to_dict
from lazyq_jax.data import DatasetError, episodes_to_transitions, load_dataset, save_dataset
from lazyq_jax.keys import purpose_key
from lazyq_jax.parallel import is_main_process
from lazyq_jax.run.rundir import as_json, write_json
from lazyq_jax.tasks import Task
from lazyq_jax.types import Transitions, pad_transitions


def log(msg: str) -> None:
    tqdm.write(msg)


@dataclasses.dataclass
class SeedData:
    """The seeds' datasets: ``stacked`` (leaves ``[S, capacity, ...]``, padded) with each
    seed's valid rows ``n_valid [S]``, and their summaries."""

    seeds: tuple[int, ...]
    stacked: Transitions
    n_valid: np.ndarray
    summaries: list[dict]

    @property
    def capacity(self) -> int:
        return int(self.stacked.r.shape[1])

    def seed_data(self, i: int) -> Transitions:
        """Seed ``i``'s valid rows (unpadded)."""
        return jax.tree.map(lambda x: x[i, : int(self.n_valid[i])], self.stacked)


def dataset_meta(config: Config, seed: int, data_version: int = 1) -> dict:
    """What a seed's static dataset is made from (as JSON gives it back): a cached file must
    match it.  ``data_version``: the task's (:attr:`~lazyq_jax.tasks.base.Task.data_version`),
    recorded when above 1, so that a task whose data gained a field re-collects old caches."""
    meta = {"task": config.task, "collect": to_dict(config.collect), "seed": int(seed)}
    if data_version != 1:
        meta["data_version"] = int(data_version)
    return as_json(meta)


def seed_dataset(task: Task, config: Config, run_dir: Path, seed: int, *, mesh: Mesh | None = None,
                 progress: bool = True) -> tuple[Transitions, dict]:
    """``data/<seed>/dataset.npz`` if it holds this task's data of this config and seed, else
    collected (with the seed's ``collect`` key) and saved there; and its summary."""
    path = run_dir / "data" / str(seed) / "dataset.npz"
    meta = dataset_meta(config, seed, task.data_version)
    if path.exists():
        try:
            data, stored = load_dataset(path)
            if stored == meta:
                return data, task.data_summary(data, config)
            log(f"data: {path} holds other data; collecting anew")
        except DatasetError as e:
            log(f"data: ignoring an unusable {path} ({e}); collecting anew")
    t = time.perf_counter()
    data = task.collect(purpose_key(seed, "collect"), config, mesh=mesh, progress=progress)
    summary = task.data_summary(data, config)
    if is_main_process():
        save_dataset(path, data, meta)
        write_json(path.parent / "summary.json", summary)
    log(f"data: seed {seed}: {data.size:,} rows ({time.perf_counter() - t:.1f} s) -> {path}")
    return data, summary


def static_data(task: Task, config: Config, run_dir: Path, seeds: Sequence[int], *,
                mesh: Mesh | None = None, progress: bool = True) -> SeedData:
    """Every seed's static dataset (collected or reused; the collection compiles once), padded
    to the longest and stacked."""
    datasets, summaries = [], []
    for seed in tqdm(seeds, desc="data (seeds)", disable=not progress or len(seeds) == 1, leave=False):
        data, summary = seed_dataset(task, config, run_dir, seed, mesh=mesh, progress=progress)
        datasets.append(data)
        summaries.append(summary)
    n_max = max(d.size for d in datasets)
    stacked = jax.tree.map(lambda *x: jnp.stack(x), *[pad_transitions(d, n_max) for d in datasets])
    return SeedData(tuple(seeds), stacked, np.array([d.size for d in datasets], np.int32), summaries)


# ----------------------------------------------------------------------------- online rounds


class OnlineRounds:
    """The online data source (``config.online.rounds > 0``): round 0 is the static dataset
    trained for ``train.cycles`` blocks; before block ``train.cycles + (r - 1) *
    online.cycles`` round ``r`` rolls out the current policy of every seed (one vmapped
    program), relabels and appends its moves (at most the round's quota of moves per
    seed); every round ends with the task's quick evaluation, recorded in
    ``<method>/rounds.jsonl``.

    Arrays are padded to :meth:`size_for` the valid rows: the capacity of the whole run
    (``online.max_moves`` moves' rows) halved as often as they allow, so the shapes, hence
    the compiled programs, change at most ``log2`` times in a run (when a round's data cross
    a power of two of the capacity), and the neighbour grids have fixed bounds (the
    task's).  Training does not depend on the padding (the shuffle draws the same order
    for the valid rows, padded batches are skipped), only its cost does: under ``vmap`` a
    padded batch is computed and dropped, and the targets are fitted for every row.
    """

    def __init__(self, task: Task, config: Config, run_dir: Path):
        o = config.online
        self.task, self.config, self.run_dir = task, config, run_dir
        self.per_move = task.rows_per_move(config)
        self.capacity = o.max_moves * self.per_move
        self.first = config.train.cycles

    def total_blocks(self) -> int:
        return self.first + self.config.online.rounds * self.config.online.cycles

    def round_end(self, r: int) -> int:
        """The block count at the end of round ``r``."""
        return self.first + r * self.config.online.cycles

    def round_starting(self, block: int) -> int | None:
        """The round whose data must be added before ``block`` runs, if any."""
        extra = block - self.first
        oc = self.config.online.cycles
        if extra >= 0 and extra % oc == 0 and extra // oc < self.config.online.rounds:
            return extra // oc + 1
        return None

    def rounds_with_data(self, block: int) -> int:
        """Rounds whose data a checkpoint after ``block`` blocks was trained on."""
        if block <= self.first:
            return 0
        return min(self.config.online.rounds, -(-(block - self.first) // self.config.online.cycles))

    def quota(self, round0_moves: int) -> int:
        o = self.config.online
        return max(0, (o.max_moves - round0_moves) // o.rounds)

    def size_for(self, rows: int) -> int:
        """The padded length for ``rows`` valid rows: the run's capacity halved while the half
        still holds ``rows`` and a training batch."""
        size, floor = self.capacity, max(int(rows), self.config.train.batch_size)
        while size % 2 == 0 and size // 2 >= floor:
            size //= 2
        return size

    def _pad(self, sd: SeedData, size: int) -> SeedData:
        stacked = jax.tree.map(lambda x: jnp.concatenate(
            [x, jnp.zeros((x.shape[0], size - x.shape[1], *x.shape[2:]), x.dtype)], 1), sd.stacked)
        return dataclasses.replace(sd, stacked=stacked)

    def padded(self, sd: SeedData) -> SeedData:
        """Round 0's data padded to :meth:`size_for` its rows (refused if the budget leaves no
        moves for the rounds)."""
        moves = int(np.max(sd.n_valid)) // self.per_move
        if moves >= self.config.online.max_moves:
            raise ConfigError(f"online.max_moves={self.config.online.max_moves} leaves no moves for the "
                              f"online rounds: round 0 already holds {moves}; raise online.max_moves "
                              "or collect less data")
        return self._pad(sd, self.size_for(int(np.max(sd.n_valid))))

    def path(self, seed: int, r: int) -> Path:
        return self.run_dir / "data" / str(seed) / f"round_{r}.npz"

    def load(self, sd: SeedData, rounds: int) -> SeedData:
        """``sd`` (round 0) with the saved moves of rounds ``1..rounds`` appended."""
        for r in range(1, rounds + 1):
            parts = []
            for seed in sd.seeds:
                part, meta = load_dataset(self.path(seed, r))
                if meta.get("seed") != seed or meta.get("round") != r:
                    raise DatasetError(f"{self.path(seed, r)} is not round {r} of seed {seed}")
                parts.append(part)
            sd = self.append(sd, parts)
        return sd

    def append(self, sd: SeedData, parts: Sequence[Transitions]) -> SeedData:
        """``parts[i]`` appended to seed ``i``'s valid rows, the padding grown to
        :meth:`size_for` the new rows where they outgrow it."""
        end = max(int(n) + p.size for n, p in zip(sd.n_valid, parts))
        if end > sd.capacity:
            sd = self._pad(sd, self.size_for(end))
        stacked, n_valid = sd.stacked, sd.n_valid.copy()
        for i, part in enumerate(parts):
            end = int(n_valid[i]) + part.size
            if end > self.capacity:
                raise AssertionError(f"internal error: {end} rows exceed the capacity {self.capacity}")
            stacked = jax.tree.map(lambda x, y, i=i, n=int(n_valid[i]): x.at[i, n:n + y.shape[0]].set(y),
                                   stacked, part)
            n_valid[i] = end
        return dataclasses.replace(sd, stacked=stacked, n_valid=n_valid)

    def collect(self, explore, policies, sd: SeedData, r: int, round0_rows: np.ndarray
                ) -> tuple[SeedData, dict]:
        """Round ``r`` for every seed: ``explore(policies, keys)`` (the task's rollouts of the
        stacked policies, one program), its moves relabelled, cut to the quota, saved to
        ``data/<seed>/round_<r>.npz`` and appended.  Returns the grown data and the
        round's counts per seed."""
        keys = jnp.stack([jax.random.fold_in(purpose_key(s, "online"), r) for s in sd.seeds])
        eps = jax.device_get(explore(policies, keys))
        counts = {k: np.asarray(v).tolist() for k, v in eps.pop("counts").items()}
        parts, kept, simulated = [], [], []
        for i, seed in enumerate(sd.seeds):
            new = episodes_to_transitions(jax.tree.map(lambda x: x[i], eps), self.per_move)
            moves = new.size // self.per_move
            quota = self.quota(int(round0_rows[i]) // self.per_move)
            if moves > quota:  # the budget: the first `quota` moves in (episode, step) order
                new = jax.tree.map(lambda x: x[: quota * self.per_move], new)
            if is_main_process():
                save_dataset(self.path(seed, r), new, {"seed": seed, "round": r})
            parts.append(new)
            simulated.append(moves)
            kept.append(min(moves, quota))
        counts.update(moves_simulated=simulated, moves_kept=kept)
        return self.append(sd, parts), counts
