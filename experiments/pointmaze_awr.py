"""Does GCIVL's actor get more out of lazy Q's value than lazy Q's greedy step does?

GCIVL (OGBench) learns V by expectile regression and extracts its policy by AWR: an actor
network that imitates the data's actions weighted by ``min(exp(alpha A), 100)`` with
``A = V(s', g) - V(s, g)`` (:mod:`lazyq_jax.agents.gcivl`).  On the maze GCIVL's own V gave
lazy Q's greedy step (Eq. 9) 50.3 % and its AWR actor 63.2 % (3 seeds, docs/pointmaze.md):
the actor smooths over the value's errors.  This script trains the same AWR actor (the same
network, goals, temperature and steps as GCIVL's) on a *frozen* lazy Q value of a trained
run, with no value loss, and evaluates it with OGBench's protocol beside the run's own
greedy policy.  A diagnostic, not a method: its budget is lazy Q's training plus the
actor's steps.

    .venv/bin/python experiments/pointmaze_awr.py runs/pm_vinit_tdata --steps 114139
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp

from lazyq_jax.agents.gcivl import GCIVL, GCIVLConfig
from lazyq_jax.run import load_run


class FrozenValueAWR(GCIVL):
    """GCIVL whose twin values are one frozen ``v_fn(s, g)`` (both members) and whose loss is
    the AWR actor's alone (the value parameters get no gradient and are never read)."""

    def __init__(self, config, problem, v_fn):
        super().__init__(config, problem)
        self.v_fn = v_fn

    def values(self, value, s, g):
        v = self.v_fn(s, g)
        return jnp.stack([v, v])

    def loss(self, params, target_value, b, b_actor=None):
        return self.actor_loss(params, b if b_actor is None else b_actor)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("run_dir", help="a pointmaze run directory with a trained lazy Q")
    p.add_argument("--steps", type=int, default=114_139,
                   help="actor steps (default: GCIVL 3 x 128's equal-time budget)")
    p.add_argument("--width", type=int, default=128)
    p.add_argument("--alpha", type=float, default=10.0, help="AWR temperature (OGBench: 10)")
    p.add_argument("--out", default=None, help="JSON (default: RUN_DIR/awr.json)")
    args = p.parse_args()
    loaded = load_run(args.run_dir, "lazy")
    config, seed = loaded.config, loaded.seeds[0]
    if config.task != "pointmaze":
        raise SystemExit(f"{args.run_dir} is a {config.task} run, not pointmaze")
    data = loaded.data.seed_data(0)
    n_valid = jnp.int32(loaded.data.n_valid[0])
    v_fn = loaded.agent.value_fn(loaded.state())
    cfg = GCIVLConfig(width=args.width, depth=4, batch_size=1024, gamma=config.train.gamma,
                      steps=args.steps, alpha=args.alpha)
    agent = FrozenValueAWR(cfg, loaded.agent.problem, v_fn)
    state = agent.init(jax.random.fold_in(jax.random.PRNGKey(seed), 7), data)
    block = jax.jit(agent.run_block)
    t = time.perf_counter()
    for b in range(agent.blocks):
        state, metrics = block(state, data, None, n_valid)
        print(f"block {b + 1}/{agent.blocks}: actor_loss {float(metrics['actor_loss']):.3f} "
              f"weight_mean {float(metrics['weight_mean']):.2f} adv {float(metrics['adv']):.4f} "
              f"({time.perf_counter() - t:.0f} s)", flush=True)
    train_s = time.perf_counter() - t
    stack = lambda tree: jax.tree.map(lambda x: x[None], tree)
    results = {"run_dir": args.run_dir, "seed": seed, "steps": args.steps, "width": args.width,
               "alpha": args.alpha, "actor_seconds": train_s}
    for name, ag, pol in (("AWR actor on lazy Q's V", agent, agent.policies(stack(state), None, None)),
                          ("lazy Q's greedy step (Eq. 9)", loaded.agent,
                           loaded.agent.policies(loaded.states, loaded.data.stacked, loaded.data.n_valid))):
        t = time.perf_counter()
        ev = loaded.task.evaluate(ag.act, pol, config, [seed])
        results[name] = ev.per_seed[0]["tasks"]
        print(f"{name}: {loaded.task.log_line(ev.per_seed[0])} ({time.perf_counter() - t:.0f} s)",
              flush=True)
    out = Path(args.out) if args.out else Path(args.run_dir) / "awr.json"
    out.write_text(json.dumps(results, indent=1))
    print(f"-> {out}")


if __name__ == "__main__":
    main()
