"""Old against new in one process: the paper-case ``search_all`` (and ``build_index``) of an
earlier checkout beside the current package, timed alternately (the machine's speed drifts
by 15-30 % between runs and processes, so only an alternating A/B in one process says
whether a change made the search faster).  ``--space 2a`` (``3a``, ``4a``, ``6a``, ``3v``)
times the general search (``neighbours.nd``'s ``build_index_nd`` / ``search_all_nd``) on
``bench_neighbours_nd.py``'s data of that case instead, and ``--data run/data/0/dataset.npz``
a run's dataset (its ``s`` and ``g``; give the task's ``--radius-s``/``--radius-g``/``--k``),
searched the way ``find_neighbours`` would.  Both versions' results (same key) are compared
element by element: a speed change must not change a neighbourhood.

The old package is copied from ``--old`` (a checkout, e.g. ``git worktree add /tmp/old
9fad38e``) into a temporary folder as ``lazyq_old`` (its imports renamed), so both import
side by side.  Same data as ``bench_neighbours.py`` (N = Q = 1M, k = 20).

    git worktree add /tmp/old 9fad38e
    flock /tmp/lazyq_bench.lock .venv/bin/python experiments/bench_neighbours_ab.py --old /tmp/old
    flock /tmp/lazyq_bench.lock .venv/bin/python experiments/bench_neighbours_ab.py --old /tmp/old --space 3a
    .venv/bin/python experiments/bench_neighbours_ab.py --old /tmp/old \
        --data runs/pm/data/0/dataset.npz --radius-s 0.5 --radius-g 1.0     # pointmaze's settings
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
from bench_neighbours import GROWTH, RG, RS, K, paper_like_data
from bench_neighbours_nd import make_data


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
    ap.add_argument("--space", default="paper",
                    help="paper (the grid's search) or a general case of bench_neighbours_nd.py: 2a, 3a, 4a, 6a, 3v")
    ap.add_argument("--data", help="a dataset .npz with arrays s [N, d_s] and g (optional) instead of --space")
    ap.add_argument("--k", type=int, default=K)
    ap.add_argument("--radius-s", type=float, default=RS)
    ap.add_argument("--radius-g", type=float, default=RG)
    args = ap.parse_args()
    import lazyq_jax.neighbours as new

    with tempfile.TemporaryDirectory() as tmp:
        old = import_old(args.old, tmp)
        k, rs, rg = args.k, args.radius_s, args.radius_g
        if args.data:
            with np.load(args.data) as f:
                s, g = f["s"].astype(np.float32), (f["g"].astype(np.float32) if "g" in f.files else None)
        elif args.space == "paper":
            s, g = paper_like_data(args.n)
        else:
            s, g, _ = make_data(args.n, int(args.space[:-1]), {"a": "angle", "v": "vector"}[args.space[-1]])
        grid = new.is_grid_space(s, g)  # as find_neighbours decides
        args.space = args.data or args.space

        def build(m):
            if grid:
                return m.build_index(s, g, k=k, radius_s=rs, radius_g=rg, growth=GROWTH, max_level=0)
            return m.nd.build_index_nd(s, g, k=k, radius_s=rs, radius_g=rg, growth=GROWTH)

        def search(m, index, key):
            return (m.search_all if grid else m.nd.search_all_nd)(index, key, s, g)

        versions = {"old": old, "new": new}
        times = {f"{v} {what}": [] for v in versions for what in ("build", "search")}
        results = {}
        for name, m in versions.items():  # compile both first
            results[name] = jax.block_until_ready(search(m, build(m), jax.random.key(0)))
        same = all(np.array_equal(np.asarray(getattr(results["old"], f)), np.asarray(getattr(results["new"], f)))
                   for f in ("idx", "level", "count"))
        print(f"space {args.space}: old and new neighbourhoods (key 0) {'identical' if same else 'DIFFER'}")
        for r in range(args.repeats):
            order = list(versions.items()) if r % 2 else list(versions.items())[::-1]
            for name, m in order:
                t0 = time.perf_counter()
                index = jax.block_until_ready(build(m))
                t1 = time.perf_counter()
                jax.block_until_ready(search(m, index, jax.random.key(r + 1)))
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
