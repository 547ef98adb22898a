"""QRL's training step on this machine: OGBench's IQE against the package's, in one process.

* ``ogbench``: OGBench's ``GCIQEValue`` as published (a sort of the ``2k`` end points), with
  autodiff's gradient;
* ``package``: ``lazyq_jax.agents.qrl.iqe_components`` (no sort: each interval adds its part
  beyond the farthest end of the intervals that start before it, that end gathered at the
  arg-max), with autodiff's gradient.

Each variant trains a block of ``--steps`` QRL steps at OGBench's point-maze settings (batch
1024, the given width, latent 512, 2-D states and actions) after compiling it; the variants
alternate ``--repeats`` times and the table gives medians.  Both compute the same
function (tests/test_qrl.py checks values and gradients against each other).

    .venv/bin/python experiments/bench_qrl.py                 # width 128, 50 steps, 3 repeats
    .venv/bin/python experiments/bench_qrl.py --width 512 --steps 20
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import numpy as np
from _common import alternating  # the script's own folder is on sys.path

from lazyq_jax.agents import qrl
from lazyq_jax.agents.base import Problem
from lazyq_jax.types import Transitions

PACKAGE = qrl.iqe_components
VARIANTS = {"ogbench": qrl.iqe_components_sorted, "package": PACKAGE}


def data(n: int = 100_000) -> Transitions:
    rng = np.random.default_rng(0)
    s = rng.uniform(0, 20, (n, 2)).astype(np.float32)
    a = rng.uniform(-1, 1, (n, 2)).astype(np.float32)
    f = jnp.asarray
    return Transitions(s=f(s), a=f(a), s_next=f(s + 0.2 * a), r=-jnp.ones(n),
                       g=f(rng.uniform(0, 20, (n, 2)).astype(np.float32)), done=jnp.zeros(n, bool))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--width", type=int, default=128)
    p.add_argument("--steps", type=int, default=50)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--variants", default="ogbench,package", help=f"comma-separated: {', '.join(VARIANTS)}")
    args = p.parse_args()
    unknown = set(args.variants.split(",")) - set(VARIANTS)
    if unknown:
        p.error(f"unknown variants {sorted(unknown)}; choose from {', '.join(VARIANTS)}")
    d = data()
    agent = qrl.make(qrl.QRLConfig(width=args.width, steps=args.steps, blocks=1),
                     Problem(action_length=1.0, action_set="box"))
    blocks = {}
    for name in args.variants.split(","):
        qrl.iqe_components = VARIANTS[name]  # iqe() looks it up at trace time
        state = agent.init(jax.random.PRNGKey(0), d)
        block = jax.jit(lambda st: agent.run_block(st, d)).lower(state).compile()
        jax.block_until_ready(block(state))
        blocks[name] = (block, state)
    qrl.iqe_components = PACKAGE
    times = alternating({name: (lambda b=b, s=s: b(s)) for name, (b, s) in blocks.items()}, args.repeats)
    print(f"QRL, batch 1024, width {args.width}, latent 512, {args.steps} steps a block, "
          f"median of {args.repeats} (alternating)")
    print("| IQE | steps/s | ms a step |")
    print("|---|---|---|")
    for name, ts in times.items():
        med = float(np.median(ts))
        print(f"| {name} | {args.steps / med:.2f} | {1e3 * med / args.steps:.1f} |")


if __name__ == "__main__":
    main()
