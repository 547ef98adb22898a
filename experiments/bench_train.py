"""Training-step throughput of the value network vs this machine's sgemm rate.

For each width: one jitted epoch (shuffle + all minibatches in ``lax.scan``) on
``--rows`` synthetic rows.  FLOPs are counted analytically as the dense-layer
matmuls only, forward + backward = 3 x 2 x sum(fan_in x fan_out) per row (XLA's
cost analysis counts a ``scan`` body once, so it cannot be used for a whole epoch);
BatchNorm, ReLU, Adam and the gathers are extra work not counted as FLOPs.
Prints GFLOP/s, the fraction of the measured sgemm rate, and the projected time
of the paper's 10 x 10 epochs over ``--rows`` rows (training only).

    .venv/bin/python experiments/bench_train.py [--widths 32 64 128 256] [--rows 995200]
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import numpy as np
from _common import timed  # the script's own folder is on sys.path

from lazyq_jax.config import TrainConfig
from lazyq_jax.train import make_train
from lazyq_jax.types import Transitions


def sgemm_rate(n=2048, repeats=5):
    _, _, sec = timed(jax.jit(lambda x: x @ x), jnp.ones((n, n), jnp.float32), repeats=repeats)
    return 2 * n**3 / sec / 1e9


def dense_flops_per_row(width: int, depth: int, n_in: int = 4) -> float:
    macs = n_in * width + (depth - 2) * width * width + width
    return 3 * 2 * macs


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--widths", type=int, nargs="+", default=[32, 64, 128, 256])
    ap.add_argument("--batch-sizes", type=int, nargs="+", default=[4096])
    ap.add_argument("--rows", type=int, default=995_200)
    ap.add_argument("--repeats", type=int, default=2)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    n = args.rows
    data = Transitions(s=jnp.asarray(rng.uniform(-1, 1, (n, 2)), jnp.float32),
                       a=jnp.zeros((n, 2)), s_next=jnp.zeros((n, 2)), r=jnp.zeros(n),
                       g=jnp.asarray(rng.uniform(-np.pi, np.pi, n), jnp.float32),
                       done=jnp.zeros(n, bool))
    y = jnp.asarray(rng.normal(size=n), jnp.float32)
    peak = sgemm_rate()
    print(f"sgemm 2048^3: {peak:.0f} GFLOP/s  ({jax.devices()[0].platform}, "
          f"{jax.local_device_count()} device(s))")
    print(f"{'width':>5} {'batch':>6} | {'epoch s':>8} {'GFLOP/s':>8} {'of sgemm':>8} | "
          f"{'100 epochs':>10} | first s (compile + run)")
    for width in args.widths:
        for batch in args.batch_sizes:
            trainer = make_train(TrainConfig(width=width, batch_size=batch), action_length=0.1)
            state = trainer.init(jax.random.PRNGKey(0), data)
            key = jax.random.PRNGKey(1)
            _, compile_s, sec = timed(jax.jit(trainer.epoch), state, data, y, key, repeats=args.repeats)
            flops = dense_flops_per_row(width, trainer.config.depth) * (n // batch) * batch
            rate = flops / sec / 1e9
            print(f"{width:>5} {batch:>6} | {sec:>8.2f} {rate:>8.1f} {rate / peak:>8.1%} | "
                  f"{100 * sec:>9.0f}s | {compile_s:.1f}")


if __name__ == "__main__":
    main()
