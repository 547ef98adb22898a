"""Is lazy Q's bound on the maze its value or its operator?  Lazy Q's policy and Bellman
operator fed with the walls-aware optimal value ``V*`` instead of the trained one.

Measurements on one trained lazy run (its first seed, its data, its neighbourhoods):

* **Oracle policy.**  Eq. (9)'s greedy action from the local fit over the dataset, with the
  neighbours' bootstrapped values ``y_j = r_j + gamma (1 - done_j) V(s'_j, g_j)`` taken from
  ``V*``, from ``V_line`` (the walls ignored) and from the trained ``V``; each evaluated with
  OGBench's protocol (the run's ``eval`` settings).  If ``V*`` succeeds where the trained
  ``V`` does not, the local policy is not what bounds lazy Q: its value is.
* **Fixed point.**  The targets of Eq. (8) (the fit over each row's neighbourhood, max over
  the box, clipped) computed from ``V*`` and from the trained ``V``, against ``V*`` at the
  rows (with the brackets of the run's ``train.target_steps``, or ``--target-steps``: each
  row's multi-step return along its trajectory), over all rows with the goal apart from the
  state and over the wall pairs
  (pointmaze_walls.py): the mean error of ``T V*`` is the operator's own bias (Eq. 7's max,
  the linear model across walls-shaped values), that of ``T V`` against ``V`` is how far
  training is from its fixed point.
* **Radius probe** (``--probe-radius``): ``T(V*) - V*`` and ``T(V_line) - V_line`` on the
  wall pairs by the state's distance from a wall, for the exact Bellman backup (OGBench's
  env step over a grid of box actions) and for Eq. (8)'s target at other state radii: how
  much a backup tells the walls-aware value from the straight-line one.
* **Two-level step** (``--subgoal-steps H``): the lazy policy with ``neighbours.subgoal_steps
  = H`` (:func:`lazyq_jax.policy.lazy_subgoals`) on the run's data with the run's V or the
  ``--values``' (``--only-values``), without retraining.

``V*`` and ``V_line`` are pointmaze_walls.py's (a BFS over a 0.25 grid of free positions;
accurate to a few steps).

    .venv/bin/python experiments/pointmaze_oracle.py runs/pm_goaloff \
        --values runs/pm_ogb:gcivl:width=128:steps=114139          # policy and fixed point
    .venv/bin/python experiments/pointmaze_oracle.py runs/pm_vinit --skip-fixed-point \
        --skip-policy --probe-radius 0.5 0.25 0.15 0.1 --pairs 100000 \
        --out runs/pm_vinit/radius_probe.json                          # the radius probe
    .venv/bin/python experiments/pointmaze_oracle.py runs/pm_lazy_s0 --skip-fixed-point \
        --only-values --values runs/pm_ogb:gcivl:width=128:steps=114139 --subgoal-steps 25 \
        --out runs/pm_lazy_s0/oracle_sub.json      # the two-level step on GCIVL's V
    .venv/bin/python experiments/pointmaze_oracle.py --table runs/pm_*/oracle_sub.json   # over seeds
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from scipy.stats import spearmanr

from lazyq_jax import agents
from lazyq_jax.keys import purpose_key
from lazyq_jax.local_model import fit_with_offsets, neighbour_offsets
from lazyq_jax.neighbours import find_neighbours
from lazyq_jax.neighbours.query import stack_policy_indices
from lazyq_jax.policy import LazyPolicy, policy_index
from lazyq_jax.run import load_run
from lazyq_jax.stats import format_ci, t_interval
from lazyq_jax.targets import (bootstrap_values, evaluate_in_batches, in_sample_target, lazy_target,
                               multi_step_transitions)
from lazyq_jax.tasks.pointmaze.maze import MAZE_UNIT, STEP_SCALE, get_maze

sys.path.insert(0, str(Path(__file__).parent))
from pointmaze_walls import RADIUS, WALL_STEPS, Geodesic, value_of  # noqa: I001


CLEARANCE = (0.0, 0.1, 0.25, 0.5, 1.0, np.inf)  # bins of the state's distance from a wall


def clearance(maze, s: np.ndarray) -> np.ndarray:
    """How far the point's ball (radius 0.7) at ``s [n, 2]`` is from the nearest wall box."""
    walls = maze.ij_to_xy(np.argwhere(maze.map == 1))
    out = np.full(len(s), np.inf)
    for w in walls:  # a few dozen boxes
        gap = np.maximum(np.abs(s - w) - MAZE_UNIT / 2, 0.0)
        out = np.minimum(out, np.linalg.norm(gap, axis=1))
    return out - RADIUS


def scored_rows(rng, pairs, s, g, geo, gamma):
    """``pairs`` rows drawn by ``rng`` among those with the goal apart from the state (sorted),
    ``V*`` there and which of them are wall pairs (the detour adds >= WALL_STEPS steps)."""
    apart = np.flatnonzero(np.any(s != g, axis=1))
    rows = np.sort(rng.choice(apart, min(pairs, apart.size), replace=False))
    d_star = geo.length(s[rows], g[rows])
    wall = d_star / STEP_SCALE - np.abs(s[rows] - g[rows]).max(1) / STEP_SCALE >= WALL_STEPS
    return rows, value_of(d_star, gamma), wall


def model_offsets(model, s, g, ii, rows):
    """The covariates of the local model ``model`` for the neighbourhoods ``ii [rows, k]`` of
    ``rows``: None (Eq. 4), the state offsets, or the state and goal offsets."""
    if model == "action":
        return None
    with_goal = model == "action+state+goal"
    return neighbour_offsets(jnp.asarray(s)[ii], jnp.asarray(s[rows]),
                             jnp.asarray(g)[ii] if with_goal else None,
                             jnp.asarray(g[rows]) if with_goal else None)


def run_target(train, a_nb, y_nb, offsets, action_length, action_set, clip=True):
    """The run's own Eq. (8) target from the neighbours' values ``y_nb`` (its
    ``train.target_max``: over the action set, the neighbours' actions, or the in-sample
    expectile of the values moved to the row): ``(alpha, target, clip_active)``."""
    alpha, beta, moved = fit_with_offsets(a_nb, y_nb, offsets=offsets)
    if train.target_max == "expectile":
        return (alpha, *in_sample_target(moved, train.target_expectile))
    over = a_nb if train.target_max == "data" else None
    return (alpha, *lazy_target(alpha, beta, y_nb, action_length, clip, action_set, over))


def fixed_point(args, agent, data, seed, n, s, g, geo, gamma, config, loaded, tables, results):
    """T V against V* (and the trained V) at sampled rows; see the module docstring.  For a
    run with ``train.bootstrap_goal="row"`` or ``train.target_max="next"`` only the trained V
    against V* (the T's here are the tabulated lazy backup's, not such a run's)."""
    rng = np.random.default_rng(0)
    rows, v_star, wall = scored_rows(rng, args.pairs, s, g, geo, gamma)
    v_rows_net = np.asarray(agent.value_fn(loaded.state())(jnp.asarray(s[rows]), jnp.asarray(g[rows])), np.float64)
    gap = v_rows_net - v_star
    results["fixed_point"]["trained V - V*"] = {
        part: {"mean": float(gap[m].mean()), "mean_abs": float(np.abs(gap[m]).mean())}
        for part, m in (("all", np.ones_like(wall)), ("wall pairs", wall))}
    print(f"trained V - V*: {json.dumps(results['fixed_point']['trained V - V*'])}", flush=True)
    if config.train.bootstrap_goal == "row" or config.train.target_max == "next":
        print("the tabulated lazy backup's T is not this run's (train.bootstrap_goal='row' or "
              "target_max='next'); skipped", flush=True)
        return
    t = time.perf_counter()
    nb = agent.prepare(seed, data, n, 0)
    idx = np.asarray(nb.idx[:n])
    print(f"neighbourhoods: {time.perf_counter() - t:.0f} s", flush=True)
    clear = clearance(get_maze(config.collect.maze), s[rows])
    ii = jnp.asarray(idx[rows])
    offsets = model_offsets(config.neighbours.local_model, s, g, ii, rows)
    a_nb = jnp.asarray(np.asarray(data.a[:n]))[ii]
    for name in ("V* (walls)", "trained V"):
        y = tables[name]
        y_nb = jnp.asarray(y)[ii]
        c, action_set = agent.problem.action_length, agent.problem.action_set
        alpha, target, clipped = run_target(config.train, a_nb, y_nb, offsets, c, action_set)
        _, unclipped, _ = run_target(config.train, a_nb, y_nb, offsets, c, action_set, clip=False)
        target, unclipped = np.asarray(target, np.float64), np.asarray(unclipped, np.float64)
        ref = v_star if name.startswith("V*") else v_rows_net
        entry = {}
        parts = [("all", np.ones_like(wall)), ("wall pairs", wall)]
        parts += [(f"state {lo}-{hi} from a wall", (clear >= lo) & (clear < hi))
                  for lo, hi in itertools.pairwise(CLEARANCE)]
        for part, m in parts:
            err = target[m] - ref[m]
            entry[part] = {"rows": int(m.sum()), "mean_error": float(err.mean()),
                           "mean_abs_error": float(np.abs(err).mean()),
                           "mean_error_unclipped": float((unclipped[m] - ref[m]).mean()),
                           "mean_alpha_error": float((np.asarray(alpha, np.float64)[m] - ref[m]).mean()),
                           "clipped": float(np.asarray(clipped)[m].mean()),
                           "spearman_with_V*": float(spearmanr(target[m], v_star[m]).statistic)}
        results["fixed_point"][f"T({name}) against {'V*' if name.startswith('V*') else 'V'}"] = entry
        print(f"T({name}): {json.dumps(entry)}", flush=True)


def exact_backup(maze, s, g, wall, clear, geo, gamma, v_star, v_line, grid=11):
    """The true Bellman backup ``-1 + gamma max_a V(step(s, a), g)`` (OGBench's env step,
    an ``grid x grid`` grid of box actions) of ``V*`` and ``V_line`` against themselves, on
    the wall pairs by the state's distance from a wall: what the lazy backup's
    ``T(V) - V`` (:func:`radius_probe`) would be if its local model saw the walls."""
    u = np.linspace(-1.0, 1.0, grid)
    actions = np.stack(np.meshgrid(u, u), -1).reshape(-1, 2)
    out = {}
    for lo, hi in itertools.pairwise(CLEARANCE):
        m = np.flatnonzero(wall & (clear >= lo) & (clear < hi))[:2000]
        if m.size == 0:
            continue
        nxt = maze.step(s[m, None, :], actions[None])          # [rows, A, 2]
        gg = np.broadcast_to(g[m, None, :], nxt.shape).reshape(-1, 2)
        flat = nxt.reshape(-1, 2)
        best_star = value_of(geo.length(flat, gg), gamma).reshape(m.size, -1).max(1)
        best_line = value_of(np.abs(flat - gg).max(1), gamma).reshape(m.size, -1).max(1)
        out[f"wall pairs, state {lo}-{hi} from a wall"] = {
            "rows": int(m.size),
            "T(V*) - V*": float((-1.0 + gamma * best_star - v_star[m]).mean()),
            "T(V_line) - V_line": float((-1.0 + gamma * best_line - v_line[m]).mean())}
    return out


def radius_probe(args, agent, data, seed, n, s, g, s2, geo, gamma, config, tables, results):
    """Which values are fixed points of Eq. (8)'s backup, for other neighbourhood radii:
    ``T(V*) - V*`` and ``T(V_line) - V_line`` (the walls ignored) at the scored rows, over the
    wall pairs and by the state's distance from a wall.  Where ``T(V_line) = V_line`` the
    backup cannot tell the walls from open space: value iteration has no reason to leave
    the straight-line value.  The true Bellman backup of ``V_line`` is lower next to a wall
    (a step into it is lost)."""
    nc = config.neighbours
    rng = np.random.default_rng(0)
    rows, v_star, wall = scored_rows(rng, args.pairs, s, g, geo, gamma)
    v_line = value_of(np.abs(s[rows] - g[rows]).max(1), gamma)
    maze = get_maze(config.collect.maze)
    clear = clearance(maze, s[rows])
    c, action_set = agent.problem.action_length, agent.problem.action_set
    a_all = jnp.asarray(np.asarray(data.a[:n]))
    out = {"exact backup": exact_backup(maze, s[rows], g[rows], wall, clear, geo, gamma, v_star, v_line)}
    print(f"exact backup: {json.dumps(out['exact backup'])}", flush=True)
    for radius_s, radius_g in itertools.product(args.probe_radius, args.probe_radius_g or [nc.radius_g]):
        t = time.perf_counter()
        nb = find_neighbours(purpose_key(seed, "neighbours"), s, g, s[rows], g[rows], k=nc.k,
                             radius_s=radius_s, radius_g=radius_g, growth=nc.growth)
        ii = jnp.asarray(nb.idx)
        offsets = model_offsets(nc.local_model, s, g, ii, rows)
        a_nb = a_all[ii]
        level = np.asarray(nb.level)
        key = f"radius_s={radius_s} radius_g={radius_g}"
        out[key] = entry = {"level0": float((level == 0).mean()), "mean_level": float(level.mean())}
        for name, ref in (("V* (walls)", v_star), ("V_line (no walls)", v_line)):
            y_nb = jnp.asarray(tables[name])[ii]
            _, target, _ = run_target(config.train, a_nb, y_nb, offsets, c, action_set)
            err = np.asarray(target, np.float64) - ref
            entry[name] = errors_by_wall_distance(err, wall, clear)
        print(f"{key} ({time.perf_counter() - t:.0f} s): {json.dumps(entry)}", flush=True)
    results["radius_probe"] = out


def errors_by_wall_distance(err, wall, clear) -> dict:
    """The mean of ``err`` over all scored rows, the wall pairs, and the wall pairs by the
    state's distance from a wall (``CLEARANCE``'s bins), with the rows in each."""
    parts = [("all", np.ones_like(wall)), ("wall pairs", wall)]
    parts += [(f"wall pairs, state {lo}-{hi} from a wall", wall & (clear >= lo) & (clear < hi))
              for lo, hi in itertools.pairwise(CLEARANCE)]
    return {part: {"rows": int(m.sum()), "mean_error": float(err[m].mean())} for part, m in parts if m.any()}


def subgoal_policy(value_fn, p: dict, action_length: float, action_set: str, steps: int) -> LazyPolicy:
    """The lazy policy's two-level step (``neighbours.subgoal_steps``,
    :func:`lazyq_jax.policy.lazy_subgoals`) over one run's data with any learned
    ``value_fn(s, g)``: neighbourhoods in state space, subgoals ``steps`` ahead on the
    neighbours' trajectories, local models with state offsets.  ``p``: the arrays of
    ``main``'s ``sg`` (stacked over one seed)."""
    return LazyPolicy(p["index"], p["actions"], jnp.zeros(p["actions"].shape[:2], jnp.float32),
                      jnp.full(1, action_length, jnp.float32), action_set, states=p["states"],
                      next_states=p["next"], value_apply=lambda _, s, g: value_fn(s, g),
                      subgoal_steps=steps, traj_last=p["last"])


def policy_table(paths) -> None:
    """The policy's success with each value over the seeds of several oracle.json files: mean
    [95 % t interval] of the 5-task success, and each task's mean."""
    runs = [json.loads(Path(p).read_text()) for p in paths]
    for r in runs:  # "V of METHOD (RUN)" as written by an earlier version: the method only
        r["policy"] = {k.split(" (")[0] if k.startswith("V of") else k: v for k, v in r["policy"].items()}
    print(f"seeds {[r['seed'] for r in runs]}\n")
    print("| V in the policy's y_j | success | per seed | task 1 | task 2 | task 3 | task 4 | task 5 |")
    print("|---|---|---|---|---|---|---|---|")
    for name in runs[0]["policy"]:
        if not all(name in r["policy"] for r in runs):
            continue
        per = [r["policy"][name] for r in runs]
        rates = [x["success_rate"] for x in per]
        tasks = [np.mean([x["per_task"][i]["success_rate"] for x in per]) for i in range(5)]
        print(f"| {name} | {format_ci(t_interval(rates))} | "
              f"{' / '.join(f'{100 * m:.1f}' for m in rates)} | "
              + " | ".join(f"{100 * v:.1f} %" for v in tasks) + " |")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("run_dir", nargs="?", help="a pointmaze run directory with a trained lazy Q")
    p.add_argument("--table", nargs="*", default=None, metavar="ORACLE_JSON",
                   help="only print the policy table over seeds of these oracle.json files")
    p.add_argument("--method", default="lazy")
    p.add_argument("--pairs", type=int, default=200000, help="rows scored for the fixed point")
    p.add_argument("--target-steps", type=int, default=None,
                   help="the fixed point's brackets as train.target_steps = H (each row's multi-step "
                        "return along its trajectory); default: the run's own")
    p.add_argument("--values", nargs="*", default=[], metavar="RUN_DIR:METHOD",
                   help="also the policy with other trained values (e.g. GCIVL's V of the same seed)")
    p.add_argument("--only-values", action="store_true",
                   help="evaluate the policy only with the --values tables (not V*, V_line, the run's V)")
    p.add_argument("--subgoal-steps", type=int, nargs="*", default=[],
                   help="also the two-level step (subgoal_policy) with each learned V, a subgoal this "
                        "many steps ahead on the neighbours' trajectories (HIQL's: 25)")
    p.add_argument("--subgoal-only", action="store_true",
                   help="evaluate only the --subgoal-steps policies")
    p.add_argument("--skip-fixed-point", action="store_true")
    p.add_argument("--skip-policy", action="store_true")
    p.add_argument("--probe-radius", type=float, nargs="*", default=[],
                   help="state radii for the fixed-point probe of V* and V_line (none: no probe)")
    p.add_argument("--probe-radius-g", type=float, nargs="*", default=[],
                   help="goal radii for that probe (default: the run's)")
    p.add_argument("--out", default=None, help="oracle.json (default: RUN_DIR/oracle.json)")
    args = p.parse_args()
    if args.table is not None:
        return policy_table(args.table)
    if args.run_dir is None:
        p.error("give a run directory (or --table)")
    loaded = load_run(args.run_dir, args.method)
    config, agent, sd, seed = loaded.config, loaded.agent, loaded.data, loaded.seeds[0]
    if config.task != "pointmaze":
        raise SystemExit(f"{args.run_dir} is a {config.task} run, not pointmaze")
    gamma = config.train.gamma
    n = int(sd.n_valid[0])
    data = sd.seed_data(0)
    s, s2, g = (np.asarray(x[:n]) for x in (data.s, data.s_next, data.g))
    r, done = np.asarray(data.r[:n]), np.asarray(data.done[:n])
    t = time.perf_counter()
    geo = Geodesic(get_maze(config.collect.maze))
    print(f"geodesics: {len(geo.nodes)} nodes ({time.perf_counter() - t:.0f} s)", flush=True)

    def table(v_next):  # y_j of every row
        return np.asarray(bootstrap_values(jnp.asarray(r), jnp.asarray(done), jnp.asarray(v_next), gamma))

    v_star_next = value_of(geo.length(s2, g), gamma).astype(np.float32)
    v_line_next = value_of(np.abs(s2 - g).max(1), gamma).astype(np.float32)
    v_trained = agent.value_fn(loaded.state())
    learned = {} if args.only_values else {"trained V": v_trained}  # value functions for --query-goal

    def at_next_of(v, states):  # V(states_j, g_j) of every row, in chunks
        return np.asarray(evaluate_in_batches(v, jnp.asarray(states), jnp.asarray(g), 65536))

    def at_next(v):  # V(s'_j, g_j) of every row
        return at_next_of(v, s2)

    v_net_next = at_next(v_trained)
    tables = {"V* (walls)": table(v_star_next), "V_line (no walls)": table(v_line_next),
              "trained V": table(v_net_next)}
    others = {}  # the --values' tables
    for spec in args.values:
        run_dir, method = spec.split(":", 1)
        other = load_run(run_dir, method)
        if other.seeds[0] != seed:
            raise SystemExit(f"{spec}: seed {other.seeds[0]}, not the lazy run's {seed}")
        fn = other.agent.value_fn(other.state())
        name = f"V of {method.split(':steps=')[0]}"
        learned[name] = fn
        others[name] = table(at_next(fn))
    tables.update(others)
    results: dict = {"run_dir": args.run_dir, "seed": seed, "policy": {}, "fixed_point": {}}

    # ---- the fixed point: T V at the rows (the run's neighbourhoods of block 0), with the
    # brackets of the run's train.target_steps (or --target-steps)
    if not args.skip_fixed_point:
        steps = config.train.target_steps if args.target_steps is None else args.target_steps
        fp_tables = tables
        if steps > 1:
            paths, disc = multi_step_transitions(jax.tree.map(lambda x: x[:n], data), steps, gamma)
            s2h = np.asarray(paths.s_next)
            fp_tables = {name: np.asarray(bootstrap_values(paths.r, paths.done, jnp.asarray(v), disc))
                         for name, v in (("V* (walls)", value_of(geo.length(s2h, g), gamma).astype(np.float32)),
                                         ("trained V", at_next_of(v_trained, s2h)))}
        results["fixed_point"]["target_steps"] = steps
        fixed_point(args, agent, data, seed, n, s, g, geo, gamma, config, loaded, fp_tables, results)

    if args.probe_radius:
        radius_probe(args, agent, data, seed, n, s, g, s2, geo, gamma, config, tables, results)

    # ---- the policy with each value table
    if getattr(agent, "subgoal_steps", 0):  # the tabulated values need the one-level policy
        nb_flat = dataclasses.replace(agent.config.neighbours, subgoal_steps=0)
        agent = agents.make("lazy", dataclasses.replace(agent.config, neighbours=nb_flat), problem=agent.problem)
    base = agent.policies(loaded.states, sd.stacked, sd.n_valid)

    def evaluate(label, policy):  # OGBench's protocol for seed 0, with Eq. (9)'s lazy_policy
        t = time.perf_counter()
        ev = loaded.task.evaluate(agent.act, policy, config, [seed])
        results["policy"][label] = ev.per_seed[0]["tasks"]
        print(f"policy with {label}: {loaded.task.log_line(ev.per_seed[0])} "
              f"({time.perf_counter() - t:.0f} s)", flush=True)

    no_tables = args.skip_policy or args.subgoal_only
    for name, y in ({} if no_tables else others if args.only_values else tables).items():
        values = np.zeros(np.shape(base.values), np.float32)
        values[0, :n] = y
        evaluate(name, base.replace(values=jnp.asarray(values)))
    if args.subgoal_steps and not args.skip_policy:
        # the state-space neighbour index and the arrays the two-level step reads (one seed)
        nc = config.neighbours
        index = stack_policy_indices([policy_index(s, None, k=nc.k, radius_s=nc.radius_s,
                                                   radius_g=nc.radius_g, growth=nc.growth,
                                                   max_level=nc.max_level, n_valid=n)])
        sg = {"index": index, "actions": jnp.asarray(np.asarray(data.a[:n]))[None],
              "states": jnp.asarray(s)[None], "next": jnp.asarray(s2)[None],
              "last": jnp.asarray(np.asarray(data.traj_last[:n]))[None]}
        for steps in args.subgoal_steps:
            for name, fn in learned.items():
                evaluate(f"{name}, subgoals {steps} steps ahead",
                         subgoal_policy(fn, sg, agent.problem.action_length, agent.problem.action_set, steps))
    out = Path(args.out) if args.out else Path(args.run_dir) / "oracle.json"
    out.write_text(json.dumps(results, indent=1))
    print(f"-> {out}")


if __name__ == "__main__":
    main()
