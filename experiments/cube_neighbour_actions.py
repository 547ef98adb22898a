"""Can any step chosen from lazy Q's state neighbourhoods act on cube-single-play?

``experiments/cube_value.py`` showed that lazy Q's Eq. (9) step fails on the cube even with
GCIVL's V.  This script asks whether the *neighbourhoods* can act at all, whatever rule picks
the action and whatever linear model: for each evaluation state ``s`` it takes the ``k``
neighbours of ``phi(s)`` in the run's play data (lazy Q's policy index, the task's feature
map and the run's radii; no goal in the search, so every neighbour is valued at the query's
own goal ``g``), values each neighbour's own move by its one-step advantage under a trained V,
``A_j = V(s'_j, g) - V(s_j, g)`` (``--value RUN:METHOD``, e.g. GCIVL's, whose AWR actor
reaches 75 % on this data), and acts by one of the rules

* ``bc``: the neighbours' mean action (nearest-neighbour behaviour cloning, no V);
* ``awr``: the ``exp(alpha A_j)``-weighted mean action (GCIVL's actor objective, Park et al.
  2024, solved in the neighbourhood instead of by a network; ``--alpha``, OGBench's cube 10);
* ``best``: the action of the largest ``A_j`` (no model: the in-sample argmax);
* ``lazy``: Eq. (5-6)'s fit ``A_j ~ alpha + beta . a_j`` and Eq. (9)'s argmax over the
  neighbours' own actions (``neighbours.greedy="data"``), the advantage removing the value's
  variation across the neighbours' states;
* ``own``: the ``--value`` run's own policy (e.g. GCIVL's actor), the reference row;

in the run's feature space, the grasp-relative ones below or a map learned from the data
(``--features learned:PATH``, ``experiments/learned_space.py``; ``--value learned:PATH``
values the moves by that map's ``-||phi(s) - phi(g)||``), evaluated by the task's protocol
(OGBench's 5 tasks, ``--episodes`` per task, seed 0), with
what the episodes did: the share whose cube moved more than 2 cm, or was lifted more than 2 cm,
the median over episodes of the effector's closest approach to the cube and of the cube's
closest approach to its target (beside its distance at the start).

    .venv/bin/python experiments/cube_neighbour_actions.py --lazy runs/cube \\
        --value runs/cube_gcivl:gcivl:width=256 --rules own,bc,awr,best,lazy --episodes 10
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from lazyq_jax.local_model import fit_local_linear
from lazyq_jax.neighbours.query import PolicyIndex, build_policy_index, query_policy, stack_policy_indices
from lazyq_jax.policy import in_sample_greedy
from lazyq_jax.run import load_run
from lazyq_jax.targets import values_at_goals
from lazyq_jax.tasks.cube.env import OBS
from learned_space import load_phi  # experiments/: run from the repository root or experiments/

RULES = ("bc", "awr", "best", "lazy", "own")


def relative_cube_features(s):
    """``phi(s) = (effector - cube (3), gripper opening (1), cube position (3))`` ``[..., 7]``
    (observation units): the grasp's coordinates and where the cube is (which decides the way
    to its target)."""
    return jnp.concatenate([s[..., OBS["effector_pos"]] - s[..., OBS["cube_pos"]], s[..., OBS["gripper_opening"]],
                            s[..., OBS["cube_pos"]]], -1)


def relative_features(s):
    """:func:`relative_cube_features` without the cube's x and y: ``(effector - cube, gripper
    opening, cube height)`` ``[..., 5]``, the same wherever on the table the cube lies."""
    r = relative_cube_features(s)
    return jnp.concatenate([r[..., :4], r[..., 6:]], -1)


def metric_value(phi: Callable) -> Callable:
    """HILP's value of a learned map (experiments/learned_space.py): ``V(s, g) = -||phi(s) -
    phi(g)||``, the temporal distance to the goal in the map's units."""
    return lambda s, g: -jnp.linalg.norm(phi(s) - phi(g), axis=-1)


@struct.dataclass
class NeighbourActs:
    """What a step reads (stacked over one seed for the task's ``vmap``)."""

    index: PolicyIndex
    actions: jax.Array  # [N, n_a]
    s: jax.Array  # [N, d_s] the neighbours' states
    s_next: jax.Array  # [N, d_s] their next states


def translated_values(v: Callable, s_nb, s, g):
    """``V(s_nb[b, j], g_bj)`` ``[B, k]`` at the query's goal moved with each neighbour's cube:
    ``g_bj``'s cube target is ``g[b]``'s plus ``cube(s_nb[b, j]) - cube(s[b])``, so that it
    stands to the neighbour's cube as the query's goal stands to the query's (the table's
    translation invariance; the rest of an OGBench goal is arbitrary)."""
    cube = OBS["cube_pos"]
    shift = s_nb[..., cube] - s[:, None, cube]
    gg = jnp.broadcast_to(g[:, None], s_nb.shape[:2] + g.shape[1:])
    gg = gg.at[..., cube].add(shift)
    return v(s_nb.reshape(-1, s_nb.shape[-1]), gg.reshape(-1, g.shape[-1])).reshape(s_nb.shape[:2])


def act_of(rule: str, alpha: float, phi: Callable | None, v: Callable, translate: bool = False) -> Callable:
    """``act_of(policy) -> act(key, s [B, d_s], g [B, d_g]) -> actions [B, n_a]`` for ``rule``
    (``translate``: each neighbour valued at the query's goal moved with its cube,
    :func:`translated_values`)."""
    def act(p: NeighbourActs, key, s, g):
        nb = query_policy(p.index, key, s if phi is None else phi(s), None)
        rows, valid = jnp.maximum(nb.idx, 0), nb.idx >= 0
        a = p.actions[rows]  # [B, k, n_a]
        if rule == "bc":  # no value: the 2k network evaluations a step are skipped
            adv = None
        elif translate:
            adv = translated_values(v, p.s_next[rows], s, g) - translated_values(v, p.s[rows], s, g)
        else:
            adv = values_at_goals(v, p.s_next[rows], g) - values_at_goals(v, p.s[rows], g)
        if rule == "bc":
            w = valid.astype(jnp.float32)
        elif rule == "awr":
            w = jnp.where(valid, jax.nn.softmax(jnp.where(valid, alpha * adv, -jnp.inf), axis=-1), 0.0)
        if rule in ("bc", "awr"):
            step = jnp.einsum("bk,bkn->bn", w, a) / jnp.maximum(w.sum(-1, keepdims=True), 1e-30)
        elif rule == "best":
            best = jnp.argmax(jnp.where(valid, adv, -jnp.inf), axis=-1)
            step = jnp.take_along_axis(a, best[:, None, None], axis=1)[:, 0]
        else:  # lazy: Eq. (5-6) on the advantages, Eq. (9) over the neighbours' actions
            _, beta = fit_local_linear(a, adv, valid.astype(jnp.float32))
            step = in_sample_greedy(a, valid, beta)
        return jnp.where((nb.level >= 0)[:, None], step, 0.0)
    return lambda p: lambda key, s, g: act(p, key, s, g)


def episode_facts(rollouts) -> dict:
    """What the episodes did (seed 0): cube moved / lifted > 2 cm, the effector's closest
    approach to the cube (median over episodes, metres)."""
    eff, cube = np.asarray(rollouts.agent)[0], np.asarray(rollouts.obj)[0]  # [T + 1, B, 3]
    moved = np.linalg.norm(cube - cube[:1], axis=-1).max(0) > 0.02
    lifted = (cube[..., 2] - cube[:1, ..., 2]).max(0) > 0.02
    closest = np.linalg.norm(eff - cube, axis=-1).min(0)
    target = np.asarray(rollouts.ctx["target"])[0]  # [B, 3]
    return {"cube_moved_2cm": float(moved.mean()), "cube_lifted_2cm": float(lifted.mean()),
            "closest_approach_m_median": float(np.median(closest)),
            "target_distance_m_median": float(np.median(np.linalg.norm(cube - target, axis=-1).min(0))),
            "start_target_distance_m_median": float(np.median(np.linalg.norm(cube[0] - target, axis=-1)))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--lazy", required=True, metavar="RUN_DIR", help="a lazy Q run: its data, feature map, k, radii")
    ap.add_argument("--value", default=None, metavar="RUN_DIR:METHOD|learned:PATH",
                    help="the V that values the neighbours (default: the lazy run's own; learned:PATH: "
                    "-||phi(s) - phi(g)|| of a map learned by experiments/learned_space.py)")
    ap.add_argument("--rules", default=",".join(RULES), help=f"comma-separated, of {RULES}")
    ap.add_argument("--alpha", type=float, default=10.0, help="awr's temperature (OGBench's cube GCIVL: 10)")
    ap.add_argument("--episodes", type=int, default=10, help="episodes per task")
    ap.add_argument("--features", default="run", metavar="run|relative|relative-cube|learned:PATH",
                    help="the neighbourhoods' space: the run's feature map, relative_features, "
                    "relative_cube_features, or a map learned by experiments/learned_space.py")
    ap.add_argument("--translate-goals", action="store_true",
                    help="value each neighbour at the query's goal moved with its cube (translated_values)")
    ap.add_argument("--radius-s", type=float, default=None, help="the neighbourhoods' radius (default the run's)")
    ap.add_argument("--k", type=int, default=None, help="neighbours a step (default the run's)")
    ap.add_argument("--out", default=None, help="write the numbers as JSON here")
    args = ap.parse_args()
    rules = args.rules.split(",")
    bad = [r for r in rules if r not in RULES]
    if bad:
        ap.error(f"unknown rules {bad}; choose from {RULES}")
    if args.episodes < 1:
        ap.error("--episodes must be >= 1")
    if not (args.features in ("run", "relative", "relative-cube") or args.features.startswith("learned:")):
        ap.error(f"--features {args.features!r}: choose run, relative, relative-cube or learned:PATH")
    lazy = load_run(args.lazy, "lazy", [f"eval.episodes_per_task={args.episodes}"])
    run_dir, _, method = (args.value or f"{args.lazy}:lazy").partition(":")
    if run_dir == "learned":
        if "own" in rules:
            ap.error("--rules own needs a trained run's policy; a learned map has none")
        valued, v = None, metric_value(load_phi(method))
    else:
        valued = lazy if args.value is None else load_run(run_dir, method or "lazy")
        v = valued.agent.value_fn(valued.state())
    data = jax.tree.map(lambda x: x[0], lazy.data.stacked)
    n = int(lazy.data.n_valid[0])
    nc, phi = lazy.config.neighbours, lazy.agent.problem.features
    nc = dataclasses.replace(nc, radius_s=nc.radius_s if args.radius_s is None else args.radius_s,
                             k=nc.k if args.k is None else args.k)
    if args.features.startswith("learned:"):
        phi = load_phi(args.features.partition(":")[2])
    elif args.features != "run":
        phi = relative_features if args.features == "relative" else relative_cube_features
    x = np.asarray(jax.jit(phi)(jnp.asarray(data.s)[:n]))
    index = stack_policy_indices([build_policy_index(x, None, k=nc.k, radius_s=nc.radius_s, radius_g=nc.radius_g,
                                                     growth=nc.growth, max_level=nc.max_level)])
    one = lambda a: jnp.asarray(a)[None, :n]
    policy = NeighbourActs(index, one(data.a), one(data.s), one(data.s_next))
    out = {"lazy": args.lazy, "value": args.value or f"{args.lazy}:lazy", "episodes_per_task": args.episodes,
           "features": args.features, "translate_goals": args.translate_goals,
           "alpha": args.alpha, "neighbours": dataclasses.asdict(nc), "rules": {}}
    space = nc.features if args.features == "run" else args.features
    print(f"k={nc.k}, radius_s={nc.radius_s} in {space} features; V of {out['value']}"
          + ("; goals moved with each neighbour's cube" if args.translate_goals else ""))
    print("| rule | success | cube moved > 2 cm | cube lifted > 2 cm | effector to cube, closest | cube to target, "
          "closest (at start) |\n|---|---|---|---|---|---|")
    for rule in rules:
        t = time.perf_counter()
        if rule == "own":
            first = lambda tree: jax.tree.map(lambda a: a[:1], tree)
            own = valued.agent.policies(first(valued.states), first(valued.data.stacked), valued.data.n_valid[:1])
            ev = lazy.task.evaluate(valued.agent.act, own, lazy.config, [lazy.seeds[0]])
        else:
            ev = lazy.task.evaluate(act_of(rule, args.alpha, phi, v, args.translate_goals), policy, lazy.config, [lazy.seeds[0]])
        row = {**lazy.task.seed_rates(ev.per_seed[0]), **episode_facts(ev.rollouts["tasks"]),
               "eval_s": round(time.perf_counter() - t, 1)}
        out["rules"][rule] = row
        print(f"| {rule} | {100 * row['success_rate']:.1f} % | {100 * row['cube_moved_2cm']:.0f} % | "
              f"{100 * row['cube_lifted_2cm']:.0f} % | {100 * row['closest_approach_m_median']:.1f} cm | "
              f"{100 * row['target_distance_m_median']:.1f} cm ({100 * row['start_target_distance_m_median']:.1f} cm) |",
              flush=True)
    if args.out:
        with open(args.out, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
