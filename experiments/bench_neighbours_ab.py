"""Old against new in one process: the paper-case ``search_all`` (and ``build_index``) of an
earlier checkout beside the current package, timed alternately (the machine's speed drifts
by 15-30 % between runs and processes, so only an alternating A/B in one process says
whether a change made the search faster).

The old package is copied from ``--old`` (a checkout, e.g. ``git worktree add /tmp/old
9fad38e``) into a temporary folder as ``lazyq_old`` (its imports renamed), so both import
side by side.  Same data as ``bench_neighbours.py`` (N = Q = 1M, k = 20).

    git worktree add /tmp/old 9fad38e
    flock /tmp/lazyq_bench.lock .venv/bin/python experiments/bench_neighbours_ab.py --old /tmp/old
"""

from __future__ import annotations

import argparse
import importlib
import pathlib
import shutil
import sys
import tempfile
import time

import jax
import numpy as np

from bench_neighbours import GROWTH, K, RG, RS, paper_like_data


def import_old(checkout: str, into: str):
    src = pathlib.Path(checkout) / "lazyq_jax"
    if not (src / "neighbours").is_dir():
        raise SystemExit(f"--old {checkout}: no lazyq_jax/neighbours there (give a checkout of this repository)")
    dst = pathlib.Path(into) / "lazyq_old"
    shutil.copytree(src, dst)
    for f in dst.rglob("*.py"):
        f.write_text(f.read_text().replace("lazyq_jax", "lazyq_old"))
    sys.path.insert(0, into)
    return importlib.import_module("lazyq_old.neighbours")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--old", required=True, help="a checkout of the earlier version")
    ap.add_argument("--repeats", type=int, default=8)
    ap.add_argument("--n", type=int, default=1_000_000)
    args = ap.parse_args()
    import lazyq_jax.neighbours as new

    with tempfile.TemporaryDirectory() as tmp:
        old = import_old(args.old, tmp)
        s, g = paper_like_data(args.n)
        versions = {"old": old, "new": new}
        times = {f"{v} {what}": [] for v in versions for what in ("build", "search")}
        for name, m in versions.items():  # compile both first
            index = m.build_index(s, g, k=K, radius_s=RS, radius_g=RG, growth=GROWTH, max_level=0)
            jax.block_until_ready(m.search_all(index, jax.random.key(0), s, g))
        for r in range(args.repeats):
            order = list(versions.items()) if r % 2 else list(versions.items())[::-1]
            for name, m in order:
                t0 = time.perf_counter()
                index = jax.block_until_ready(
                    m.build_index(s, g, k=K, radius_s=RS, radius_g=RG, growth=GROWTH, max_level=0))
                t1 = time.perf_counter()
                jax.block_until_ready(m.search_all(index, jax.random.key(r + 1), s, g))
                t2 = time.perf_counter()
                times[f"{name} build"].append(t1 - t0)
                times[f"{name} search"].append(t2 - t1)
        for key, v in times.items():
            print(f"{key:12s} median {np.median(v):.3f} s   " + " ".join(f"{x:.3f}" for x in v))
        paired = np.array(times["new search"]) - np.array(times["old search"])
        print(f"search new - old, paired: median {np.median(paired):+.3f} s, new faster in "
              f"{int((paired < 0).sum())} of {len(paired)}")


if __name__ == "__main__":
    main()
