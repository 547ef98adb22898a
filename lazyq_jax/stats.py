"""Aggregates over seeds: means with 95 % confidence intervals.

A study's unit of replication is the seed: every seed has its own dataset,
neighbourhood samples, initialisation and evaluation episodes, so the seeds'
results are independent draws of the whole pipeline.  The interval is Student's t
over the seeds' values, ``mean +- t_{0.975, S-1} * sd / sqrt(S)`` (``sd`` with
``S - 1`` degrees of freedom), clipped to ``[0, 1]`` for rates.  It needs at least
two seeds; with one the interval is ``None``.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np
from scipy import stats as _scipy_stats


def t_interval(values: Sequence[float], level: float = 0.95,
               bounds: tuple[float, float] | None = (0.0, 1.0)) -> dict:
    """``{"mean", "ci95", "sd", "n"}`` of ``values`` (one per seed).

    ``ci95``: ``[low, high]`` of the Student-t interval at ``level`` (``None`` for
    fewer than two values), clipped to ``bounds`` (``None``: not clipped).
    """
    x = np.asarray(values, np.float64)
    if x.ndim != 1 or x.size == 0:
        raise ValueError(f"need a non-empty list of per-seed values, got shape {x.shape}")
    if not np.all(np.isfinite(x)):
        raise ValueError(f"per-seed values must be finite, got {x.tolist()}")
    if not 0 < level < 1:
        raise ValueError(f"level must lie in (0, 1), got {level}")
    n, mean = x.size, float(x.mean())
    if n < 2:
        return {"mean": mean, "ci95": None, "sd": None, "n": n}
    sd = float(x.std(ddof=1))
    half = float(_scipy_stats.t.ppf(0.5 + level / 2, n - 1)) * sd / math.sqrt(n)
    low, high = mean - half, mean + half
    if bounds is not None:
        low, high = max(low, bounds[0]), min(high, bounds[1])
    return {"mean": mean, "ci95": [low, high], "sd": sd, "n": n}


def format_ci(summary: dict, percent: bool = True) -> str:
    """``"97.5 % [95.1, 99.9]"`` (or without CI for a single seed)."""
    scale, unit = (100.0, " %") if percent else (1.0, "")
    text = f"{summary['mean'] * scale:.1f}{unit}"
    if summary["ci95"] is not None:
        low, high = summary["ci95"]
        text += f" [{low * scale:.1f}, {high * scale:.1f}]"
    return text
