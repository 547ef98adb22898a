"""``python -m lazyq_jax benchmark SUITE``: every dataset of a benchmark suite
(:data:`lazyq_jax.tasks.SUITES`, e.g. ``ogbench-pointmaze``: OGBench's eight pointmaze datasets)
with the same methods and seeds, resumably, into one directory, and one table.

``RUN_DIR/suite.json`` names the suite, datasets, methods, seeds and preset; ``RUN_DIR/<dataset>/``
is that dataset's ordinary run directory (:func:`lazyq_jax.run.runner.run` with ``resume``:
a finished dataset is only re-evaluated from its stored evaluation, an interrupted one goes on
from its newest checkpoints); after each dataset ``RUN_DIR/results.json`` and ``results.md``
are rewritten (:mod:`lazyq_jax.run.suite`), so an interrupted benchmark shows what it has.

*More seeds later.*  The seeds of one call train together (one program, vmapped) in one run
directory, a *seed group*.  A later call may name seeds the directory does not hold yet
(``--seeds 3`` after ``--seeds 1``): those form a new group, trained into
``RUN_DIR/<dataset>/seeds-1-2/`` (:func:`lazyq_jax.run.suite.group_dir`), and the table pools
every group's seeds; the groups a call's seeds touch are resumed as they were recorded.
Each dataset takes its task's preset (its recipe and discount; one set of lazy Q settings) and
the same ``--set`` overrides; baselines take the task's per-dataset settings
(:meth:`~lazyq_jax.tasks.base.Task.method_defaults`).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Sequence

from lazyq_jax import tasks
from lazyq_jax.config import ConfigError, override
from lazyq_jax.parallel import maybe_initialize_distributed
from lazyq_jax.run import suite
from lazyq_jax.run.rundir import RunDirError, check_methods, check_seeds, locked, write_json
from lazyq_jax.run.runner import run
from lazyq_jax.run.sources import log


def plan(name: str, datasets: Sequence[str] | None = None) -> list[str]:
    """The datasets of suite ``name`` to run (all, or ``datasets`` of it, in the suite's order)."""
    if name not in tasks.SUITES:
        raise ConfigError(f"unknown benchmark suite {name!r}; suites: {', '.join(tasks.SUITES)}")
    members = tasks.SUITES[name]
    if datasets is None:
        return list(members)
    if not datasets:
        raise ConfigError(f"no dataset chosen; leave the datasets out for every dataset of {name!r}")
    chosen = [tasks.canonical(d) for d in datasets]
    unknown = [d for d in chosen if d not in members]
    if unknown:
        raise ConfigError(f"{', '.join(unknown)}: not in suite {name!r}; its datasets: {', '.join(members)}")
    return [d for d in members if d in chosen]


def benchmark(name: str, run_dir: Path, seeds: Sequence[int], methods: Sequence[str], *,
              datasets: Sequence[str] | None = None, preset: str = "paper", sets: Sequence[str] = (),
              progress: bool = True, command: str = "") -> dict:
    """Run suite ``name``'s datasets (module docstring); returns the table's data."""
    names = plan(name, datasets)
    methods = [m.text for m in check_methods(methods)]  # before suite.json records them
    seeds = list(check_seeds(seeds))
    configs = {}
    for d in names:  # every config checked before anything runs
        configs[d] = override(tasks.preset(d, preset), list(sets))
        tasks.get(d).check(configs[d])
    maybe_initialize_distributed(configs[names[0]].parallel)  # before anything touches a device
    run_dir = Path(run_dir)
    meta = {"suite": name, "datasets": names, "methods": methods, "seeds": seeds, "seed_groups": [seeds],
            "preset": preset, "sets": sorted(sets), "command": command}
    with locked(run_dir):  # held throughout: a second benchmark of this directory is refused at once
        path = run_dir / suite.SUITE_FILE
        groups = [seeds]  # the seed groups this call runs
        if path.exists():
            old = json.loads(path.read_text())
            old["sets"] = sorted(old.get("sets", []))
            differ = [k for k in ("suite", "preset", "sets") if old.get(k) != meta[k]]
            if differ:
                raise RunDirError(f"{run_dir} holds a benchmark whose {', '.join(differ)} differ ("
                                  + "; ".join(f"{k}: {old.get(k)} there, {meta[k]} now" for k in differ)
                                  + "); resume it with the same settings or choose another --run-dir")
            old_groups = suite.seed_groups(old)
            held = {s for g in old_groups for s in g}
            new = [s for s in seeds if s not in held]
            groups = [g for g in old_groups if set(g) & set(seeds)] + ([new] if new else [])
            meta["seed_groups"] = old_groups + ([new] if new else [])
            meta["seeds"] = sorted(held | set(seeds))
            meta["datasets"] = [d for d in tasks.SUITES[name] if d in set(old["datasets"]) | set(names)]
            meta["methods"] = list(dict.fromkeys([*old["methods"], *methods]))
        write_json(path, meta)
        for i, d in enumerate(names):
            for group in groups:
                log(f"benchmark {name}: dataset {i + 1}/{len(names)}: {d}, seeds {group}")
                run(configs[d], suite.group_dir(run_dir / d, group, meta["seed_groups"]), seeds=group,
                    methods=methods, resume=True, progress=progress)
                data = suite.write(run_dir, command)
    return data
