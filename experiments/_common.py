"""What several experiments share: timing a JAX call and printing rates over seeds.

The scripts import it from their own folder (``python experiments/X.py`` puts that folder
on ``sys.path``).  Statistics are the package's (:mod:`lazyq_jax.stats`), so a table here
reads like the runner's and ``python -m lazyq_jax report``'s.
"""

from __future__ import annotations

import math
import statistics
import time

import jax

from lazyq_jax.stats import format_ci, t_interval


def timed(fn, *args, repeats: int = 1):
    """``(out, first_s, median_s)``: one call of ``fn(*args)`` (its compile, if any), then the
    median of ``repeats`` more; every call waited for (``jax.block_until_ready``)."""
    t = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    first = time.perf_counter() - t
    return out, first, statistics.median(alternating({"": lambda: fn(*args)}, repeats)[""])


def alternating(fns: dict, repeats: int) -> dict[str, list[float]]:
    """Seconds of every call ``fns[name]()`` (waited for), the names taking turns ``repeats``
    times, so that a machine shared with other work slows each of them alike."""
    times = {name: [] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            t = time.perf_counter()
            jax.block_until_ready(fn())
            times[name].append(time.perf_counter() - t)
    return times


def rate_keys(row: dict) -> list[str]:
    """The summary rates of a task's per-seed row (``task.seed_rates``), finite in this row."""
    return [k for k, v in row.items() if k.endswith("_rate") and "per_direction" not in k
            and v is not None and math.isfinite(v)]


def rates_table(table: dict[str, list[dict]], keys: list[str], extra=None, head: str = "") -> None:
    """Print a Markdown table: a row per name of ``table`` (its per-seed rows), mean [95 % CI]
    of each rate over the seeds (``extra(rows)``: one more cell), then each later row's
    difference to the first, paired by position (every list in the same seeds' order)."""
    print(f"| {head} | " + " | ".join(keys) + (" | |" if extra else " |"))
    print("|---|" + "---|" * (len(keys) + bool(extra)))
    for name, rows in table.items():
        cells = [format_ci(t_interval([r[k] for r in rows])) for k in keys]
        print(f"| {name} | " + " | ".join(cells + ([extra(rows)] if extra else [])) + " |")
    first, *others = table
    for name in others:
        if len(table[name]) != len(table[first]):
            continue  # not the same seeds: no pairs
        diffs = [format_ci(t_interval([r[k] - b[k] for r, b in zip(table[name], table[first])],
                                      bounds=None)) for k in keys]
        print(f"| {name} - {first} (paired) | " + " | ".join(diffs) + (" | |" if extra else " |"))
