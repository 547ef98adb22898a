"""Wall time and peak memory of one seed's whole pipeline against a study of S seeds.

Runs, one after the other in fresh processes, ``python -m lazyq_jax train`` (one
seed: collect, search, train, evaluate: what ``make train`` does) and ``python -m
lazyq_jax study --seeds S`` (the same pipeline for S seeds), each starting afresh
(``--overwrite``) with JAX's persistent compilation cache off
(``LAZYQ_COMPILE_CACHE=off``, so both pay their compiles), and prints wall time,
peak resident memory (from ``wait4``) and the phases' seconds from the runs' own
timing files.  The S-seed study directory is a complete study: the README's
paper-world table is read from it.

    .venv/bin/python experiments/bench_study.py [--seeds 8] [--task push] [--preset paper]
        [--one-dir runs/bench_train_1] [--many-dir runs/study_paper] [--set FIELD=VALUE ...]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path


def run(args: list[str]) -> tuple[float, float]:
    """Wall seconds and peak RSS (GB) of one child process."""
    env = {**os.environ, "LAZYQ_COMPILE_CACHE": "off", "PYTHONUNBUFFERED": "1"}
    t = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "lazyq_jax", *args], env=env)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t
    if os.waitstatus_to_exitcode(status) != 0:
        sys.exit(f"failed: {' '.join(args)}")
    return wall, usage.ru_maxrss / 1e6  # kB on Linux


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=8)
    ap.add_argument("--task", default="push")
    ap.add_argument("--preset", default="paper")
    ap.add_argument("--one-dir", type=Path, default=Path("runs/bench_train_1"))
    ap.add_argument("--many-dir", type=Path, default=Path("runs/study_paper"))
    ap.add_argument("--set", action="append", default=[])
    args = ap.parse_args()
    sets = [x for s in args.set for x in ("--set", s)]
    common = ["--task", args.task, "--preset", args.preset, "--overwrite", "--no-progress", *sets]
    phases = lambda d: {**json.loads((d / "timings.json").read_text()),
                        **json.loads((d / "lazy" / "timings.json").read_text())}
    rows = []
    wall, rss = run(["train", "--run-dir", str(args.one_dir), *common])
    rows.append((1, wall, rss, phases(args.one_dir)))
    wall, rss = run(["study", "--seeds", str(args.seeds), "--run-dir", str(args.many_dir), *common])
    rows.append((args.seeds, wall, rss, phases(args.many_dir)))
    print(f"\n{'seeds':>5} | {'wall s':>7} {'per seed':>8} | {'peak RSS':>8} | phases (s)")
    for seeds, wall, rss, timings in rows:
        phases = ", ".join(f"{k} {v}" for k, v in timings.items())
        print(f"{seeds:>5} | {wall:>7.0f} {wall / seeds:>8.0f} | {rss:>6.2f} GB | {phases}")
    (s1, w1, *_), (sn, wn, *_) = rows
    print(f"\n{sn} seeds took {wn / w1:.2f} x the wall time of 1 seed (goal <= 3 x)")


if __name__ == "__main__":
    main()
