"""A run's checkpoint per block: one orbax manager per save (``save_checkpoint``, the runner
until this change) against one manager for the whole run (``checkpoint_writer``), in the same
run, on a small state like lazy Q's on pointmaze (180 KB: a 9 x 32 x 32 network, Adam's
moments, targets).  Opening a manager lists every checkpoint already in the directory, so the first
way costs time linear in the blocks saved before.

    .venv/bin/python experiments/bench_checkpoints.py [--saves 300]
"""

from __future__ import annotations

import argparse
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np

from lazyq_jax.checkpoint import checkpoint_writer, load_checkpoint, save_checkpoint


def state_like_lazy(seed: int = 0) -> dict:
    k = jax.random.split(jax.random.key(seed), 3)
    params = {"w": jax.random.normal(k[0], (9, 32, 32)), "b": jax.random.normal(k[1], (9, 32))}
    return {"params": params, "mu": params, "nu": jax.tree.map(jnp.abs, params),
            "targets": jax.random.normal(k[2], (16_384,)), "step": jnp.asarray(0)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--saves", type=int, default=300)
    args = ap.parse_args()
    state = state_like_lazy()
    meta = {"method": "lazy"}
    times = {}
    with tempfile.TemporaryDirectory() as a, tempfile.TemporaryDirectory() as b:
        per_save = []
        for step in range(1, args.saves + 1):
            t = time.perf_counter()
            save_checkpoint(a, state, step, meta)
            per_save.append(time.perf_counter() - t)
        times["a manager per save (save_checkpoint)"] = per_save
        one = []
        with checkpoint_writer(b) as save:
            for step in range(1, args.saves + 1):
                t = time.perf_counter()
                save(state, step, meta)
                one.append(time.perf_counter() - t)
        times["one manager (checkpoint_writer)"] = one
        abstract = jax.eval_shape(lambda: state)
        restored = [load_checkpoint(d, abstract)[0] for d in (a, b)]
        same = all(bool(jnp.array_equal(x, y)) for x, y in
                   zip(jax.tree.leaves(restored[0]), jax.tree.leaves(restored[1])))
    n = args.saves
    print(f"{n} saves, state {sum(x.nbytes for x in jax.tree.leaves(state)) / 1e3:.0f} KB, "
          f"devices {jax.devices()}")
    print("| way | first 10 (median s) | last 10 (median s) | all saves (s) |")
    print("|---|---|---|---|")
    for name, ts in times.items():
        print(f"| {name} | {np.median(ts[:10]):.3f} | {np.median(ts[-10:]):.3f} | {sum(ts):.1f} |")
    print(f"the last checkpoints restore to the same state: {same}")


if __name__ == "__main__":
    main()
