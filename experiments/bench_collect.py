"""MJX data collection vs native MuJoCo on the same pushes (issue: the push world, §4).

For each batch size, the same finger starts and moves are simulated by
``jit(vmap(PushEnv.step))`` (MJX, JAX implementation, in float64 as ``collect``
uses it and in float32) and by ``mujoco.rollout`` (native, float64, 1 and 2
threads).  Two sets of pushes: drawn like the collection's ("collect": ~1.5%
touch the disk) and all aimed at the disk ("contact").  Prints pushes/s, physics
steps/s, the MJX/native ratios and the largest and 99th-percentile difference of
final disk positions, then the jit compile time of the collection function and
one paper-scale ``collect`` call.

``--world forgiving`` (MuJoCo's own drag) compares speeds with ``mujoco.rollout``;
``--world paper`` (the default; Coulomb friction that we set before every
substep) has no fast native path: its native reference steps one push at a time
from Python on the first ``--native-max`` pushes, for agreement only.

    .venv/bin/python experiments/bench_collect.py [--world paper|forgiving]
        [--batches 1024 4096 16384] [--repeats 3]
"""

from __future__ import annotations

import argparse
import math
import time

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from _common import timed  # the script's own folder is on sys.path

from lazyq_jax.data import _episode_keys
from lazyq_jax.tasks.push import FORGIVING_PUSH, CollectConfig, PushConfig, PushEnv
from lazyq_jax.tasks.push.collect import collect, make_episode_fn
from lazyq_jax.tasks.push.native import native_push


def pushes(rng, batch, contact):
    """Starts and moves like the collection's (``contact=False``), or all aimed at the disk."""
    if contact:
        ang = rng.uniform(-np.pi, np.pi, batch)
        start = rng.uniform(0.32, 0.4, batch)[:, None] * np.stack([np.cos(ang), np.sin(ang)], 1)
        turn = ang + np.pi + rng.uniform(-0.7, 0.7, batch)
    else:
        start = rng.uniform(-1, 1, (batch * 2, 2))
        start = start[np.linalg.norm(start, axis=1) > 0.31][:batch]
        turn = rng.uniform(-np.pi, np.pi, batch)
    return start.astype(np.float32), np.stack([np.cos(turn), np.sin(turn)], 1).astype(np.float32)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--batches", type=int, nargs="+", default=[1024, 4096, 16384])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--world", choices=["paper", "forgiving"], default="paper",
                    help="paper: Coulomb friction, set from Python per substep in native MuJoCo "
                    "(a reference on at most --native-max pushes, not a speed comparison); "
                    "forgiving: MuJoCo's own drag, native rollout on 1 and 2 threads")
    ap.add_argument("--native-max", type=int, default=512)
    args = ap.parse_args()
    world = PushConfig() if args.world == "paper" else FORGIVING_PUSH
    make_env = lambda: PushEnv(world)

    steps = world.substeps
    print(f"world: {args.world} ({world.friction})")
    print(f"jax {jax.__version__} on {jax.devices()[0].platform} x{jax.local_device_count()}, "
          f"mujoco {mujoco.__version__}; {steps} physics steps per push")
    print(f"{'pushes':>7} {'set':>8} {'MJX':>7} | {'MJX pushes/s':>12} {'steps/s':>9} | "
          f"{'native1 st/s':>12} {'native2 st/s':>12} | {'MJX/nat2':>8} {'MJX/nat1':>8} | "
          f"{'max |diff|':>10} {'p99 |diff|':>10} {'moved':>6}")
    rng = np.random.default_rng(0)
    for batch in args.batches:
        for contact in (False, True):
            start, action = pushes(rng, batch, contact)
            zeros = np.zeros_like(start)
            env = make_env()
            rates = {}
            # The Coulomb world's native reference steps one push at a time from Python.
            n_native = batch if world.friction == "fluid" else min(batch, args.native_max)
            for nthread in (1, 2):
                datas = [mujoco.MjData(env.mj_model) for _ in range(nthread)]
                final, _, t_nat = timed(native_push, env, start[:n_native], zeros[:n_native],
                                        action[:n_native], nthread, datas,
                                        repeats=args.repeats if n_native == batch else 1)
                rates[nthread] = n_native * steps / t_nat
            for x64 in (True, False):
                with jax.enable_x64(x64):
                    env = make_env()
                    step = jax.jit(jax.vmap(env.step))
                    state, act = env.reset(jnp.asarray(start)), jnp.asarray(action)
                    (_, delta), _, t_mjx = timed(step, state, act, repeats=args.repeats)  # compile first
                mjx_rate = batch * steps / t_mjx
                diff = np.linalg.norm(np.asarray(delta, np.float64)[:n_native] - final, axis=1)
                moved = np.mean(np.linalg.norm(final, axis=1) >= 0.01)
                print(f"{batch:>7} {'contact' if contact else 'collect':>8} "
                      f"{'float64' if x64 else 'float32':>7} | {batch / t_mjx:>12,.0f} "
                      f"{mjx_rate:>9,.0f} | {rates[1]:>12,.0f} {rates[2]:>12,.0f} | "
                      f"{mjx_rate / rates[2]:>8.2f} {mjx_rate / rates[1]:>8.2f} | "
                      f"{diff.max():>10.2e} {np.quantile(diff, 0.99):>10.2e} {moved:>6.1%}")

    cfg = CollectConfig(push=world)
    chunk = math.ceil(cfg.n_starts / math.ceil(cfg.n_starts / cfg.chunk_size))
    with jax.enable_x64(cfg.push.float64):
        keys = _episode_keys(jax.random.PRNGKey(0), 0, chunk)
        t = time.perf_counter()
        jax.jit(jax.vmap(make_episode_fn(PushEnv(cfg.push), cfg))).lower(keys).compile()
    print(f"\ncollection function (chunk of {chunk} episodes): jit compile {time.perf_counter() - t:.1f} s")
    t = time.perf_counter()
    data = collect(jax.random.PRNGKey(0), cfg, progress=False)
    print(f"paper-scale collect(): {cfg.n_starts} x {cfg.moves_per_start} moves x {cfg.n_goals} goals "
          f"-> {data.size:,} rows in {time.perf_counter() - t:.1f} s (incl. its compile)")


if __name__ == "__main__":
    main()
