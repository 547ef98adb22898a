"""Every baseline with its DEFAULT config on the synthetic line tasks with a known optimum.

Tasks (:mod:`lazyq_jax.agents.reference`; 20,000 rows each, data seed 0, agent key 0):

1. ``s`` in [-1, 1]^2, ``g`` an angle, ``u_g = (cos g, sin g)``, moves of length 0.1 on
   the circle (the task of ``tests/test_baselines.py``);
2. ``s`` in [-1, 1]^3, ``g`` one of 16 fixed unit vectors ``u`` (``g[N, 3]``), moves of
   length 0.1 on the sphere.

Reward 1 and done when ``s' . u > 0.5``; probe states (2000) have ``s . u`` in
[0, 0.45]; the optimal action points along ``u``.  Printed per agent and task: the
fraction of probe actions within 26 degrees of ``u`` and their median cos (with
``--curve``, after every block).  Chance: 52 / 360 = 14.4 % (task 1) and
(1 - cos 26 deg) / 2 = 5.1 % (task 2) of uniform directions are within 26 degrees.

    .venv/bin/python experiments/agents_synthetic.py                 # all, defaults
    .venv/bin/python experiments/agents_synthetic.py --agents iql --tasks 1 --curve \\
        --set iql.advantage_scale=none                               # IQL before the fix

Measured (defaults, 2 CPU cores; fraction within 26 degrees / median cos):

    FIGURES
"""

from __future__ import annotations

import argparse
import sys
import time

import jax
import jax.numpy as jnp

from lazyq_jax.agents import bc, dqn, iql, naf, td3bc
from lazyq_jax.agents.base import Problem
from lazyq_jax.agents.reference import line_probes, line_task, random_policy, score
from lazyq_jax.config import ConfigError

MAKERS = {"iql": (iql.make, iql.IQLConfig), "td3bc": (td3bc.make, td3bc.TD3BCConfig),
          "dqn": (dqn.make, dqn.DQNConfig), "naf": (naf.make, naf.NAFConfig),
          "bc": (bc.make, bc.BCConfig)}
TASKS = {1: (2, "angle"), 2: (3, "vector")}


def parse_value(text: str):
    for cast in (int, float):
        try:
            return cast(text)
        except ValueError:
            pass
    return {"none": None, "true": True, "false": False}.get(text.lower(), text)


def overrides(items: list[str]) -> dict[str, dict]:
    out: dict[str, dict] = {}
    for item in items:
        key, _, value = item.partition("=")
        name, _, field = key.partition(".")
        if name not in MAKERS or not field or not value:
            raise SystemExit(f"--set takes AGENT.FIELD=VALUE with AGENT in {list(MAKERS)}, "
                             f"got {item!r}")
        out.setdefault(name, {})[field] = parse_value(value)
    return out


def run(name: str, task: int, fields: dict, rows: int, seed: int, curve: bool) -> None:
    d, goal = TASKS[task]
    data = line_task(seed, rows, d, goal)
    s, g, u = line_probes(2000, d, goal)
    s, g = jnp.asarray(s), None if g is None else jnp.asarray(g)
    make, cls = MAKERS[name]
    try:
        config = cls(**fields)
    except (ConfigError, TypeError) as err:
        raise SystemExit(str(err))
    agent = make(config, Problem(action_length=0.1))
    t0 = time.perf_counter()
    init, block = jax.jit(agent.init), jax.jit(agent.run_block)
    state = init(jax.random.PRNGKey(seed), data)
    for b in range(agent.blocks):
        state, metrics = block(state, data)
        if curve or b == agent.blocks - 1:
            frac, cos = score(agent.policy(state)(None, s, g), u)
            info = " ".join(f"{k}={float(v):.4g}" for k, v in sorted(metrics.items()))
            print(f"  {name:6s} task {task} block {b + 1:2d}/{agent.blocks} step "
                  f"{int(state.step):6d}: within 26 deg {frac:.3f}, median cos {cos:.3f}"
                  f"{'  [' + info + ']' if curve else ''}", flush=True)
    print(f"{name:6s} task {task}: {frac:.3f} / {cos:.3f}  ({time.perf_counter() - t0:.0f} s; "
          f"{', '.join(f'{k}={v}' for k, v in fields.items()) or 'defaults'})", flush=True)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--agents", nargs="+", default=list(MAKERS), choices=list(MAKERS))
    p.add_argument("--tasks", nargs="+", type=int, default=[1, 2], choices=list(TASKS))
    p.add_argument("--rows", type=int, default=20_000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--curve", action="store_true", help="score after every block")
    p.add_argument("--set", nargs="*", default=[], metavar="AGENT.FIELD=VALUE")
    args = p.parse_args(argv)
    fields = overrides(args.set)
    for task in args.tasks:
        d, goal = TASKS[task]
        s, g, u = line_probes(2000, d, goal)
        frac, cos = score(random_policy(Problem(), d)(jax.random.PRNGKey(0), s, g), u)
        print(f"random task {task}: {frac:.3f} / {cos:.3f}", flush=True)
        for name in args.agents:
            run(name, task, fields.get(name, {}), args.rows, args.seed, args.curve)


if __name__ == "__main__":
    main(sys.argv[1:])
