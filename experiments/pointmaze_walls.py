"""Does a learned V(s, g) see the maze's walls?  Trained values of pointmaze runs, and the
lazy network fitted by plain regression to the walls-aware optimum, against two references.

* ``V*``: the optimal value with the walls.  Free positions of the point (a ball of radius
  0.7) on a grid of 0.25; an 8-neighbour graph whose every edge is one grid unit (a box
  action moves up to 0.2 along each axis at once, so the step count is a Chebyshev
  length); all-pairs BFS (``scipy.sparse.csgraph``).  Steps to the goal
  ``n = ceil(D / 0.2)`` for the geodesic length ``D``, ``V* = -(1 - gamma^n) / (1 - gamma)``:
  the training rows' reward (OGBench's relabelling: -1 a step until the goal *is* the
  state, ``r = success - 1`` with success only where the goal is the current state).
  An approximation (contacts, the grid), good to a few steps.
* ``V_line``: the same with ``D`` the straight Chebyshev distance (the walls ignored).

For every value model: Spearman's rank correlation with ``V*`` and with ``V_line`` on
(state, goal) pairs drawn from the training rows of the first run's first seed (pairs with
the goal at the state itself, 20 % of the rows, left out: they tie at 0), over all pairs
and over the *wall pairs* (the detour round the walls adds >= 20 steps), with 95 %
bootstrap intervals over the pairs.  A value that sees the walls ranks the wall pairs like
``V*``; one that ignores them like ``V_line``.

The *subgoal ascent* of each evaluation task (``--ascent-steps``, 25 by default: the lazy
default's ``neighbours.subgoal_steps``): from the free node nearest the task's start, move to
the node of highest V(node, goal) among all free nodes within that many steps (geodesically),
until no node there is higher; the steps from where it stops to the goal (geodesic; 0 = the
goal reached).  The two-level policy idealised: any free position is a subgoal, and the move
to it is exact.  With ``V*`` it reaches every goal; where a learned V stops short, it has a
trap at the subgoals' range: no policy that climbs it leaves.

The fits train the value network on ``(s, g) -> V*`` rows with Adam (batch 4096): the
lazy default (depth 9: 8 hidden layers of 32, batch norm) and 3 hidden layers of 128, ``--fit-steps`` each.  If they see
the walls where lazy Q's Bellman training does not, the network is not what bounds it.

    .venv/bin/python experiments/pointmaze_walls.py --runs runs/pm_goaloff:lazy \\
        runs/pm_ogb:gcivl:width=128:steps=114139 --fit-steps 10000
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
from scipy import sparse
from scipy.sparse import csgraph
from scipy.spatial import cKDTree
from scipy.stats import spearmanr

from lazyq_jax.data import load_dataset
from lazyq_jax.networks import ValueNetwork
from lazyq_jax.plots import plt
from lazyq_jax.run import load_run
from lazyq_jax.tasks.pointmaze.maze import MAZE_UNIT, STEP_SCALE, get_maze
from lazyq_jax.tasks.pointmaze.plots import draw_maze

H = 0.25  # grid spacing
RADIUS = 0.7  # the point's ball (OGBench's model)
WALL_STEPS = 20  # a wall pair: the detour adds at least this many steps


class Geodesic:
    """Free grid nodes of a maze and their all-pairs BFS lengths (in units of ``H``)."""

    def __init__(self, maze):
        x0, y0, x1, y1 = maze.bounds
        xs, ys = np.arange(x0, x1 + 1e-9, H), np.arange(y0, y1 + 1e-9, H)
        gx, gy = np.meshgrid(xs, ys)  # [ny, nx]
        walls = maze.ij_to_xy(np.argwhere(maze.map == 1))
        pts = np.stack([gx, gy], -1)
        gap = np.abs(pts[:, :, None, :] - walls[None, None]) - MAZE_UNIT / 2
        dist = np.linalg.norm(np.maximum(gap, 0.0), axis=-1).min(-1)
        free = dist >= RADIUS - 1e-9
        ids = -np.ones(free.shape, np.int64)
        ids[free] = np.arange(free.sum())
        rows, cols = [], []
        ny, nx = free.shape
        fi, fj = np.nonzero(free)
        for di, dj in ((0, 1), (1, 0), (1, 1), (1, -1)):
            ti, tj = fi + di, fj + dj
            ok = (ti >= 0) & (ti < ny) & (tj >= 0) & (tj < nx)
            ok[ok] = free[ti[ok], tj[ok]]
            if di and dj:  # a diagonal step needs both of its orthogonal steps free
                ok[ok] = free[fi[ok] + di, fj[ok]] & free[fi[ok], fj[ok] + dj]
            rows.append(ids[fi[ok], fj[ok]])
            cols.append(ids[ti[ok], tj[ok]])
        r, c = np.concatenate(rows), np.concatenate(cols)
        n = int(free.sum())
        graph = sparse.coo_matrix((np.ones(r.size), (r, c)), shape=(n, n)).tocsr()
        self.nodes = pts[free]
        self.lengths = csgraph.shortest_path(graph, directed=False, unweighted=True).astype(np.float32)
        self.tree = cKDTree(self.nodes)
        if not np.all(np.isfinite(self.lengths)):
            raise AssertionError("the free grid is not connected")

    def length(self, s: np.ndarray, g: np.ndarray) -> np.ndarray:
        """Geodesic Chebyshev length between positions (snapped to the nearest free node)."""
        _, i = self.tree.query(s)
        _, j = self.tree.query(g)
        return self.lengths[i, j] * H


def value_of(length: np.ndarray, gamma: float) -> np.ndarray:
    """``-(1 - gamma^n) / (1 - gamma)`` for ``n = ceil(length / 0.2)`` steps to the goal."""
    n = np.ceil(np.round(length / STEP_SCALE, 6))
    return -(1.0 - gamma ** n) / (1.0 - gamma)


def fit(x_s, x_g, y, width, depth, steps, seed=0, batch=4096, lr=1e-3):
    """Regress ``ValueNetwork(width, depth)`` onto ``y`` (MSE, Adam): the fitted ``V(s, g)``."""
    net = ValueNetwork(width=width, depth=depth)
    variables = net.init(jax.random.PRNGKey(seed), x_s[:2], x_g[:2])
    opt = optax.adam(lr)
    state = (variables["params"], variables["batch_stats"], opt.init(variables["params"]))
    xs, xg, yy = map(jnp.asarray, (x_s, x_g, y))

    def step(state, key):
        params, stats, opt_state = state
        rows = jax.random.randint(key, (batch,), 0, xs.shape[0])

        def loss(p):
            v, upd = net.apply({"params": p, "batch_stats": stats}, xs[rows], xg[rows], train=True,
                               mutable=["batch_stats"])
            return jnp.mean((v - yy[rows]) ** 2), upd["batch_stats"]

        (value, stats), grads = jax.value_and_grad(loss, has_aux=True)(params)
        updates, opt_state = opt.update(grads, opt_state, params)
        return (optax.apply_updates(params, updates), stats, opt_state), value

    run = jax.jit(lambda state, keys: jax.lax.scan(step, state, keys))
    state, losses = run(state, jax.random.split(jax.random.PRNGKey(seed + 1), steps))
    params, stats, _ = state
    apply = jax.jit(lambda s, g: net.apply({"params": params, "batch_stats": stats}, s, g))
    return apply, float(losses[-100:].mean())


def scores(v, v_star, v_line, wall, n_boot: int = 200) -> dict:
    """Spearman's rho of ``v`` with ``V*`` and ``V_line`` (all pairs, wall pairs), each with a
    95 % bootstrap interval over the pairs."""
    rng = np.random.default_rng(1)

    def rho(a, b):
        boot = [spearmanr(a[i], b[i]).statistic
                for i in rng.integers(len(a), size=(n_boot, len(a)))]
        return [float(spearmanr(a, b).statistic), *map(float, np.percentile(boot, [2.5, 97.5]))]

    return {"rho_star": rho(v, v_star), "rho_line": rho(v, v_line),
            "wall_rho_star": rho(v[wall], v_star[wall]), "wall_rho_line": rho(v[wall], v_line[wall])}


def ascent(geo: Geodesic, v: np.ndarray, start: int, reach: float, limit: int = 500) -> int:
    """The node where the subgoal ascent on node values ``v`` stops, from node ``start``, each
    move to the highest value within geodesic ``reach`` (grid units); ties keep the current node."""
    node = start
    for _ in range(limit):
        near = np.flatnonzero(geo.lengths[node] <= reach)
        best = near[np.argmax(v[near])]
        if v[best] <= v[node]:
            break
        node = best
    return node


def ascents(geo: Geodesic, maze, values: dict, gamma: float, steps: int) -> dict:
    """Steps left to each task's goal where the subgoal ascent of every value stops (and of V*)."""
    reach = steps * STEP_SCALE / H
    out = {}
    for i, (start_ij, goal_ij) in enumerate(maze.tasks):
        start, goal = maze.ij_to_xy(np.asarray(start_ij)), maze.ij_to_xy(np.asarray(goal_ij))
        _, first = geo.tree.query(start)
        _, target = geo.tree.query(goal)
        goals = np.broadcast_to(goal, geo.nodes.shape).astype(np.float32)
        models = {"V* (walls, approx.)": value_of(geo.lengths[:, target] * H, gamma)}
        models.update({name: np.asarray(fn(jnp.asarray(geo.nodes, jnp.float32), jnp.asarray(goals)), np.float64)
                       for name, fn in values.items()})
        out[f"task {i + 1}"] = {
            "start_steps": float(geo.lengths[first, target] * H / STEP_SCALE),
            "left": {name: float(geo.lengths[ascent(geo, v, first, reach), target] * H / STEP_SCALE)
                     for name, v in models.items()}}
    return out


def fmt(r) -> str:
    return f"{r[0]:.3f} [{r[1]:.3f}, {r[2]:.3f}]"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--runs", nargs="*", default=[], metavar="RUN_DIR:METHOD",
                   help="trained values to score (the run's first seed)")
    p.add_argument("--data", default=None, help="dataset.npz of the rows (default: the first run's)")
    p.add_argument("--pairs", type=int, default=20000)
    p.add_argument("--fit-steps", type=int, default=10000)
    p.add_argument("--gamma", type=float, default=0.99)
    p.add_argument("--ascent-steps", type=int, default=25,
                   help="the subgoal ascent's reach in steps (0: no ascent table)")
    p.add_argument("--out", default="runs/pointmaze_walls")
    args = p.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    runs = [r.split(":", 1) for r in args.runs]
    mazes = {json.loads((Path(d) / "run.json").read_text())["config"]["collect"]["maze"] for d, _ in runs}
    if len(mazes) > 1:
        raise SystemExit(f"the runs are of different mazes: {sorted(mazes)}")
    maze = get_maze(mazes.pop() if mazes else "medium")
    t = time.perf_counter()
    geo = Geodesic(maze)
    print(f"geodesics: {len(geo.nodes)} free nodes ({time.perf_counter() - t:.1f} s)", flush=True)

    if args.data:
        data_path = Path(args.data)
    elif runs:
        seed = json.loads((Path(runs[0][0]) / "run.json").read_text())["seeds"][0]
        data_path = Path(runs[0][0]) / "data" / str(seed) / "dataset.npz"
    else:
        raise SystemExit("give --data (a pointmaze dataset.npz) or --runs")
    data, _ = load_dataset(data_path)
    s, g = np.asarray(data.s), np.asarray(data.g)
    rng = np.random.default_rng(0)
    apart = np.flatnonzero(np.any(s != g, axis=1))  # the goal at the state itself: left out
    test = rng.choice(apart, args.pairs, replace=False)
    v_star = value_of(geo.length(s[test], g[test]), args.gamma)
    v_line = value_of(np.abs(s[test] - g[test]).max(1), args.gamma)
    steps_star = geo.length(s[test], g[test]) / STEP_SCALE
    steps_line = np.abs(s[test] - g[test]).max(1) / STEP_SCALE
    wall = steps_star - steps_line >= WALL_STEPS
    ref = scores(v_star, v_star, v_line, wall)
    print(f"{args.pairs} pairs from {data_path} ({len(apart) / len(s):.1%} of the rows have the goal "
          f"apart from the state): {wall.mean():.1%} are wall pairs (detour >= {WALL_STEPS} steps); "
          f"V* against V_line: all {fmt(ref['rho_line'])}, wall pairs {fmt(ref['wall_rho_line'])}",
          flush=True)

    values = {}
    for run_dir, method in runs:
        loaded = load_run(run_dir, method)
        values[f"{method.split(':steps=')[0]}, {Path(run_dir).name} seed {loaded.seeds[0]}"] = \
            loaded.agent.value_fn(loaded.state())
    if args.fit_steps:
        train = np.setdiff1d(np.arange(len(s)), test)
        y = value_of(geo.length(s[train], g[train]), args.gamma).astype(np.float32)
        for width, depth in ((32, 9), (128, 4)):
            t = time.perf_counter()
            fn, loss = fit(s[train], g[train], y, width, depth, args.fit_steps)
            name = f"fit to V*: {depth - 1} hidden x {width}, BN"
            values[name] = fn
            print(f"{name}, {args.fit_steps} steps: final mse {loss:.3f} "
                  f"({time.perf_counter() - t:.0f} s)", flush=True)

    table = {}
    print("\n| value | Spearman with V* | with V_line | wall pairs: with V* | wall pairs: with V_line |")
    print("|---|---|---|---|---|")
    for name, fn in values.items():
        v = np.asarray(fn(jnp.asarray(s[test]), jnp.asarray(g[test])), np.float64)
        table[name] = sc = scores(v, v_star, v_line, wall)
        print(f"| {name} | {fmt(sc['rho_star'])} | {fmt(sc['rho_line'])} | {fmt(sc['wall_rho_star'])} | "
              f"{fmt(sc['wall_rho_line'])} |", flush=True)
    climbs = ascents(geo, maze, values, args.gamma, args.ascent_steps) if args.ascent_steps else {}
    if climbs:
        names = list(next(iter(climbs.values()))["left"])
        print(f"\nsubgoal ascent (reach {args.ascent_steps} steps): steps from its stop to the goal "
              f"(geodesic; the start's in brackets)")
        print("| value | " + " | ".join(f"{k} ({c['start_steps']:.0f})" for k, c in climbs.items()) + " |")
        print("|---|" + "---|" * len(climbs))
        for name in names:
            print(f"| {name} | " + " | ".join(f"{c['left'][name]:.0f}" for c in climbs.values()) + " |")
    (out / "walls.json").write_text(json.dumps({"pairs": args.pairs, "wall_fraction": float(wall.mean()),
                                                "scores": table, "ascent_steps": args.ascent_steps,
                                                "ascents": climbs}, indent=1))

    # V over the maze for task 3's goal (round a wall): the optimum and every model
    x0, y0, x1, y1 = maze.bounds
    n = 100
    grid = np.stack(np.meshgrid(np.linspace(x0, x1, n), np.linspace(y0, y1, n)), -1).reshape(-1, 2)
    cells = maze.xy_to_ij(grid)
    free = maze.map[cells[:, 0], cells[:, 1]] == 0
    goal = maze.ij_to_xy(maze.tasks[2][1])
    goals = np.broadcast_to(goal, grid.shape).astype(np.float32)
    panels = {"V* (walls, approx.)": value_of(geo.length(grid, goals), args.gamma)}
    panels.update({name: np.asarray(fn(jnp.asarray(grid, jnp.float32), jnp.asarray(goals)))
                   for name, fn in values.items()})
    fig, axes = plt.subplots(1, len(panels), figsize=(3.4 * len(panels), 3.6), squeeze=False)
    for ax, (name, v) in zip(axes[0], panels.items()):
        im = ax.imshow(np.where(free, v, np.nan).reshape(n, n), origin="lower",
                       extent=(x0, x1, y0, y1), cmap="viridis")
        draw_maze(ax, maze)
        ax.plot(*goal, "r*", ms=10)
        ax.set_title(name, fontsize=7)
        fig.colorbar(im, ax=ax, fraction=0.046)
    fig.suptitle("V(s, g) for task 3's goal", fontsize=10)
    fig.tight_layout()
    fig.savefig(out / "walls_task3.png", dpi=110)
    print(f"-> {out / 'walls.json'}, {out / 'walls_task3.png'}")


if __name__ == "__main__":
    main()
