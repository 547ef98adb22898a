"""What JAX's persistent compilation cache saves a second ``make train``.

Runs ``python -m lazyq_jax train`` (the paper preset, evaluation included, as ``make
train``) three times in fresh processes, each starting the run afresh
(``--overwrite``): once with the cache off, then twice with one new, empty cache
directory (the first fills it, the second reads it).  With ``JAX_LOG_COMPILES=1`` it
sums the seconds of the logged "Finished XLA compilation" lines (a program loaded
from the cache logs milliseconds there) and counts the logged cache hits.

    .venv/bin/python experiments/bench_compile_cache.py [--run-dir runs/bench_cache] [--set ...]
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

COMPILED = re.compile(r"Finished XLA compilation of .* in ([0-9.eE+-]+) sec")
HIT = "Persistent compilation cache hit"


def run(run_dir: Path, cache: str, sets: list[str]) -> tuple[float, float, int]:
    env = {**os.environ, "LAZYQ_COMPILE_CACHE": cache, "JAX_LOG_COMPILES": "1"}
    t = time.perf_counter()
    out = subprocess.run([sys.executable, "-m", "lazyq_jax", "train", "--run-dir", str(run_dir),
                          "--overwrite", "--no-progress", *sets], env=env, capture_output=True,
                         text=True)
    wall = time.perf_counter() - t
    if out.returncode != 0:
        sys.exit(out.stderr[-3000:])
    log = out.stderr + out.stdout
    seconds = [float(m.group(1)) for m in COMPILED.finditer(log)]  # a cache hit logs ~ms
    return wall, sum(seconds), log.count(HIT)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--run-dir", type=Path, default=Path("runs/bench_cache"))
    ap.add_argument("--set", action="append", default=[])
    args = ap.parse_args()
    sets = [x for s in args.set for x in ("--set", s)]
    rows = [("cache off", *run(args.run_dir, "off", sets))]
    with tempfile.TemporaryDirectory() as cache:
        rows.append(("cache empty (fills it)", *run(args.run_dir, cache, sets)))
        rows.append(("cache filled", *run(args.run_dir, cache, sets)))
    print(f"{'run':<24} | {'wall s':>7} | {'XLA compile s':>13} | {'cache hits':>10}")
    for name, wall, compile_s, n in rows:
        print(f"{name:<24} | {wall:>7.1f} | {compile_s:>13.1f} | {n:>10}")


if __name__ == "__main__":
    main()
