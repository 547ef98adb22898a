"""Learn a space for lazy Q's neighbourhoods from the data alone: HILP's temporal-distance map.

Lazy Q's neighbourhoods need a space where "near" means "one action apart".  On a robot's raw
observations (cube-single-play: 28-D) no hand-made map tried here serves (docs/cube.md).
This script learns one from the trajectories, with no task knowledge: the Hilbert
representation of HILP (Park, Kreiman & Levine, "Foundation Policies with Hilbert
Representations", ICML 2024): a map ``phi: S -> R^d`` whose distances are temporal distances,
trained as a goal-conditioned value of the metric form

    V(s, g) = -|| phi(s) - phi(g) ||_2

by OGBench's IVL loss (:func:`lazyq_jax.agents.gcivl.ivl_value_loss`: the twin value, the
expectile regression towards ``r + gamma m V^t(s', g)``, the Polyak target), with HILP's
goals (:func:`lazyq_jax.agents.goals.fresh_goals` with ``p_cur`` 0, ``p_traj`` 0.625
geometric, else a random state) and its settings (``gamma`` 0.99, expectile 0.9, Adam 3e-4,
target rate 0.005, LayerNorm MLP); ``d`` (``--dim``, 8 by default: lazy Q's neighbour searches
take at most 10 dimensions a side, HILP uses 32-512) and the network (``--width``, ``--depth``)
sized for this CPU.  The twin's first member is the map (as HILP's ``get_phis``).

It trains on a run's data (``--run RUN_DIR``, its first seed; trajectory data with state goals),
saves the map (``--out PATH``, flax msgpack, read back by :func:`load_phi`) and reports what
the space holds along the data's own trajectories: Spearman's rho of ``-||phi(s_t) -
phi(s_{t+h})||`` with ``-h`` (all pairs and those that move the cube more than 4 cm, as
``experiments/cube_value.py`` reports for the values), the distance by ``h``, and the distance
to the ``k``-th nearest row of the data (the neighbourhoods' radius in this space) and, on the
cube's observations, how far apart the ``k`` nearest rows are in the grasp's coordinates
(effector - cube, metres: the largest distance from the query's).  Use it
with ``experiments/cube_neighbour_actions.py --features learned:PATH``.

    .venv/bin/python experiments/learned_space.py --run runs/cube --out runs/cube_phi.msgpack \\
        --steps 20000
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import flax.serialization
import jax
import jax.numpy as jnp
import numpy as np
import optax
from scipy.stats import spearmanr

from lazyq_jax.agents.common import MLP, apply_ensemble, init_ensemble, polyak, uniform_rows
from lazyq_jax.agents.gcivl import ivl_value_loss
from lazyq_jax.agents.goals import GoalMix, fresh_goals
from lazyq_jax.run import load_run
from lazyq_jax.tasks.cube.env import OBS, OBS_DIM, XYZ_SCALE

#: HILP's value goals (its ``value_p_*goal``): never the row itself, 0.625 a geometric later
#: state of the trajectory, else a random state.
HILP_GOALS = GoalMix(p_cur=0.0, p_traj=0.625, geom=True)
BANDS = (1, 3, 10, 30, 100, 300, 1000)


def phi_net(width: int, depth: int, dim: int) -> MLP:
    """``phi``: ``depth`` LayerNorm MLP layers, the last ``dim`` wide (HILP's GCMetricValue)."""
    return MLP(width=width, depth=depth, out=dim)


def metric_values(net: MLP, params, s: jax.Array, g: jax.Array) -> jax.Array:
    """``[2, B]``: ``-||phi_i(s) - phi_i(g)||`` for both members of the twin."""
    d = apply_ensemble(net, params, s) - apply_ensemble(net, params, g)
    return -jnp.sqrt(jnp.sum(d * d, axis=-1) + 1e-12)


def train_phi(data, n_valid: int, key: jax.Array, *, width: int, depth: int, dim: int, steps: int,
              batch_size: int, gamma: float = 0.99, expectile: float = 0.9, tau: float = 0.005,
              lr: float = 3e-4, block: int = 500, log=print):
    """The twin's parameters after ``steps`` IVL steps on ``data`` (trajectory rows with
    ``traj_last``); progress every ``block`` steps through ``log``."""
    if data.traj_last is None:
        raise SystemExit("learned_space: the run's data are not trajectories (no traj_last); "
                         "HILP's goals are later states of each row's trajectory")
    net = phi_net(width, depth, dim)
    key, k0 = jax.random.split(key)
    params = init_ensemble(net, k0, data.s[:1])
    opt = optax.adam(lr)
    carry = (params, params, opt.init(params))

    def loss(p, target, b):
        return ivl_value_loss(metric_values(net, target, b.s_next, b.g), metric_values(net, target, b.s, b.g),
                              metric_values(net, p, b.s, b.g), b, gamma, expectile)

    def step(data, carry, k):
        params, target, opt_state = carry
        k_rows, k_goals = jax.random.split(k)
        rows = uniform_rows(k_rows, batch_size, n_valid)
        b = jax.tree.map(lambda x: x[rows], data)
        g, r, done = fresh_goals(data, rows, k_goals, n_valid, gamma, HILP_GOALS)
        b = b.replace(g=g, r=r, done=done)
        grads, info = jax.grad(loss, has_aux=True)(params, target, b)
        updates, opt_state = opt.update(grads, opt_state, params)
        target = polyak(target, params, tau)  # OGBench/HILP: the parameters before the update
        return (optax.apply_updates(params, updates), target, opt_state), info

    # the data are an argument, not a constant folded into the program
    run_block = jax.jit(lambda data, carry, keys: jax.lax.scan(lambda c, k: step(data, c, k), carry, keys))
    t0 = time.perf_counter()
    for done_steps in range(0, steps, block):
        n = min(block, steps - done_steps)
        key, kb = jax.random.split(key)
        carry, info = run_block(data, carry, jax.random.split(kb, n))
        info = {k: float(v[-1]) for k, v in info.items()}
        log(f"step {done_steps + n}/{steps}: value_loss {info['value_loss']:.3f}, v_mean {info['v_mean']:.1f}, "
            f"v_min {info['v_min']:.1f} ({time.perf_counter() - t0:.0f} s)")
    return net, carry[0]


def save_phi(path: str | Path, net: MLP, params) -> None:
    """The map's first member and its shape, as flax msgpack."""
    first = jax.tree.map(lambda x: np.asarray(x[0]), params)
    blob = {"width": net.width, "depth": net.depth, "dim": net.out, "params": first}
    Path(path).write_bytes(flax.serialization.msgpack_serialize(blob))


def load_phi(path: str | Path):
    """``phi(s [..., d_s]) -> [..., d]`` (jitted) from :func:`save_phi`'s file."""
    blob = flax.serialization.msgpack_restore(Path(path).read_bytes())
    net = phi_net(int(blob["width"]), int(blob["depth"]), int(blob["dim"]))
    params = jax.tree.map(jnp.asarray, blob["params"])
    return jax.jit(lambda s: net.apply(params, s))


def trajectory_pairs(traj_last: np.ndarray, n: int, max_h: int, rng: np.random.Generator):
    """``(rows, h)``: rows whose trajectory goes on at least ``h`` steps, ``h`` log-uniform."""
    rows = rng.integers(0, len(traj_last), 8 * n)
    h = np.exp(rng.uniform(0, np.log(max_h), 8 * n)).astype(np.int64)
    keep = rows + h <= traj_last[rows]
    return rows[keep][:n], h[keep][:n]


def describe(phi, data, n_valid: int, *, pairs: int, k: int, queries: int, seed: int = 0) -> dict:
    """The space along the trajectories (module docstring) and its k-th neighbour distances."""
    rng = np.random.default_rng(seed)
    s = np.asarray(data.s[:n_valid])
    x = np.concatenate([np.asarray(phi(jnp.asarray(s[i:i + 65536]))) for i in range(0, n_valid, 65536)])
    rows, h = trajectory_pairs(np.asarray(data.traj_last[:n_valid]), pairs, 1000, rng)
    dist = np.linalg.norm(x[rows] - x[rows + h], axis=-1)
    out = {"spearman_all": float(spearmanr(-dist, -h)[0])}
    cube, effector = OBS["cube_pos"], OBS["effector_pos"]
    if s.shape[-1] == OBS_DIM:  # OGBench's cube observation (positions offset and x10)
        moved = np.linalg.norm(s[rows, cube] - s[rows + h, cube], axis=-1) / XYZ_SCALE > 0.04
        out["spearman_cube_moved"] = float(spearmanr(-dist[moved], -h[moved])[0])
        out["pairs_cube_moved"] = int(moved.sum())
    out["distance_by_h"] = {f"[{lo}, {hi})": float(dist[(h >= lo) & (h < hi)].mean())
                            for lo, hi in zip(BANDS[:-1], BANDS[1:]) if ((h >= lo) & (h < hi)).any()}
    q = x[rng.integers(0, n_valid, queries)]
    q_rows = rng.integers(0, n_valid, queries)
    q = x[q_rows]
    kth, near = [], []
    for i in range(0, queries, 64):  # brute force over all rows, 64 queries at a time
        d2 = ((q[i:i + 64, None, :] - x[None]) ** 2).sum(-1)
        part = np.argpartition(d2, k, axis=1)[:, :k + 1]  # the query itself and its k nearest
        kth.append(np.sqrt(np.take_along_axis(d2, part, 1).max(1)))  # k-th neighbour besides itself
        near.append(part)
    kth, near = np.concatenate(kth), np.concatenate(near)
    out[f"kth_neighbour_distance_quantiles_k{k}"] = {p: float(np.quantile(kth, p / 100)) for p in (10, 50, 90)}
    if s.shape[-1] == OBS_DIM:  # how far apart in the grasp's coordinates the neighbours are, metres
        grasp = (s[:, effector] - s[:, cube]) / XYZ_SCALE
        spread = np.linalg.norm(grasp[near] - grasp[q_rows][:, None], axis=-1).max(1)
        out[f"neighbours_grasp_spread_m_quantiles_k{k}"] = {p: float(np.quantile(spread, p / 100))
                                                            for p in (10, 50, 90)}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--run", required=True, metavar="RUN_DIR", help="a trained run whose data (first seed) to learn on")
    ap.add_argument("--method", default="lazy", help="the run's method whose data to read (default lazy)")
    ap.add_argument("--out", required=True, metavar="PATH", help="where to save the map (msgpack)")
    ap.add_argument("--dim", type=int, default=8, help="the space's dimension (<= 10 for lazy Q's searches)")
    ap.add_argument("--width", type=int, default=256)
    ap.add_argument("--depth", type=int, default=4, help="layers, the last one --dim wide")
    ap.add_argument("--steps", type=int, default=20000)
    ap.add_argument("--batch-size", type=int, default=1024)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--pairs", type=int, default=20000, help="trajectory pairs for the report")
    ap.add_argument("--k", type=int, default=20, help="the neighbour whose distance the report gives")
    ap.add_argument("--queries", type=int, default=256, help="rows whose k-th neighbour distance is measured")
    ap.add_argument("--describe-only", action="store_true",
                    help="no training: report on the map already saved at --out (its .json gets the new numbers)")
    args = ap.parse_args()
    for name in ("dim", "width", "depth", "steps", "batch_size", "pairs", "queries", "k"):
        if getattr(args, name) < 1:
            ap.error(f"--{name.replace('_', '-')} must be >= 1")
    run = load_run(args.run, args.method)
    data = jax.tree.map(lambda x: x[0], run.data.stacked)
    n = int(run.data.n_valid[0])
    report_path = Path(args.out).with_suffix(".json")
    if args.describe_only:
        report = json.loads(report_path.read_text())
    else:
        t0 = time.perf_counter()
        net, params = train_phi(data, n, jax.random.PRNGKey(args.seed), width=args.width, depth=args.depth,
                                dim=args.dim, steps=args.steps, batch_size=args.batch_size)
        save_phi(args.out, net, params)
        report = {"run": args.run, "dim": args.dim, "width": args.width, "depth": args.depth, "steps": args.steps,
                  "batch_size": args.batch_size, "seed": args.seed, "train_s": round(time.perf_counter() - t0, 1)}
    report.update(describe(load_phi(args.out), data, n, pairs=args.pairs, k=args.k, queries=args.queries))
    report_path.write_text(json.dumps(report, indent=1))
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
