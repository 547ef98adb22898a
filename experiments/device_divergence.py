"""How far do 1- and 2-device training drift apart, compared with rounding noise?

On the paper-scale dataset of ``runs/paper`` (run ``make train`` first), trains one
cycle (``--epochs`` epochs, targets included) from the same initial state three ways,
in one process with 2 host devices:

* A: one device (no mesh);
* B: one device, initial parameters scaled by ``1 + 1e-7`` (a rounding-sized nudge);
* C: two devices (data-parallel, synchronised batch norm).

Prints the largest parameter difference and the largest difference of V over
100,000 dataset points for A-B and A-C.  If A-C is about A-B, the device count
changes the result only as much as any rounding difference does.

    .venv/bin/python experiments/device_divergence.py [--epochs 10] [--run-dir runs/paper]
"""

from __future__ import annotations

import argparse
import os


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--epochs", type=int, default=10)
    ap.add_argument("--run-dir", default="runs/paper")
    args = ap.parse_args()
    os.environ["XLA_FLAGS"] = "--xla_force_host_platform_device_count=2"
    import dataclasses

    import jax
    import numpy as np

    from lazyq_jax.config import Config
    from lazyq_jax.data import load_dataset
    from lazyq_jax.parallel import make_mesh, put, replicated
    from lazyq_jax.pipeline import neighbours_for, run_keys
    from lazyq_jax.train import make_train_for

    data, collect_config, seed = load_dataset(os.path.join(args.run_dir, "dataset.npz"))
    config = Config(seed=seed, collect=collect_config)
    config = dataclasses.replace(config, train=dataclasses.replace(config.train, epochs=args.epochs))
    idx = neighbours_for(config, data)
    mesh = make_mesh(2)
    one, two = make_train_for(config), make_train_for(config, mesh=mesh)
    state0 = one.init(run_keys(config)["train"])
    nudged = state0.replace(params=jax.tree.map(lambda p: p * (1 + 1e-7), state0.params))
    a = jax.jit(one.run_cycle)(state0, data, idx)[0]
    b = jax.jit(one.run_cycle)(nudged, data, idx)[0]
    c = jax.device_get(jax.jit(two.run_cycle)(put(state0, replicated(mesh)),
                                              put(data, replicated(mesh)), idx)[0])

    def param_diff(x, y):
        return max(float(np.abs(np.asarray(p) - np.asarray(q)).max())
                   for p, q in zip(jax.tree.leaves(x.params), jax.tree.leaves(y.params)))

    s, g = data.s[:100_000], data.g[:100_000]
    v = {name: np.asarray(one.value_fn(st)(s, g)) for name, st in (("a", a), ("b", b), ("c", c))}
    print(f"one cycle of {args.epochs} epochs ({args.epochs * (data.size // config.train.batch_size)} "
          f"Adam steps); V spans [{v['a'].min():.2f}, {v['a'].max():.2f}]")
    print(f"  1 device vs 1 device nudged by 1e-7: params {param_diff(a, b):.3g}, "
          f"V {np.abs(v['a'] - v['b']).max():.3g}")
    print(f"  1 device vs 2 devices:               params {param_diff(a, c):.3g}, "
          f"V {np.abs(v['a'] - v['c']).max():.3g}")


if __name__ == "__main__":
    main()
