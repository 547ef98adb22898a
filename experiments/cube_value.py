"""Does a trained V(s, g) on cube-single-play rank states by how far the goal is?

Along the play data's own trajectories the oracle's progress is known: the goal ``s_{t+h}``
is reached from ``s_t`` in at most ``h`` steps, so a value that sees the task falls with
``h``.  For each run (``RUN:METHOD``) this draws ``--pairs`` (state, later state of the same
episode) pairs from the run's first seed's data, ``h`` log-uniform in ``[1, --max-h]``, and
reports

* ``V`` by ``h`` (mean over the pairs in each band) beside ``V*(h) = -(1 - gamma^h) / (1 -
  gamma)``, the value of reaching the goal in exactly ``h`` steps (OGBench's reward: -1 a step
  until the goal *is* the state; the play path is one way, not necessarily the shortest, so
  ``V* >= V*(h)`` holds only along the path);
* Spearman's rank correlation of ``V`` with ``-h`` over all pairs, and over the pairs whose
  cube moves between ``s_t`` and ``s_{t+h}`` (the ones a manipulation value must get right:
  a goal that only moves the arm is the easy half), with 95 % bootstrap intervals.

``--lazy-policy RUN_DIR`` then separates the value from lazy Q's operator: lazy Q's policy of
that run (its neighbourhoods, Eq. 9, its acting settings; ``--set`` changes them) acts with
each run's V in its table ``y_j = r_j + gamma (1 - done_j) V(s'_j, g_j)``, evaluated by the
task's protocol (OGBench's 5 tasks x ``eval.episodes_per_task``; seed 0's episodes).  If
another agent's V makes lazy Q's step succeed, lazy Q's V is what bounds it; if not, the step.
It also reports how linear each V is in the actions of lazy Q's training neighbourhoods
(``--fit-rows`` of them): the local fit's R^2 of ``y_j ~ alpha + beta . a_j`` (Eq. 5-6) over
the k neighbours, beside ``n_a / (k - 1)``, what a fit of pure noise scores on average, and
what those neighbourhoods hold for the fit (:func:`composition`: distinct trajectories and
actions, the spread of the neighbours' actions, rank-deficient designs).

    .venv/bin/python experiments/cube_value.py --runs runs/cube:lazy runs/cube_gcivl:gcivl:width=256 \
        --lazy-policy runs/cube --set neighbours.greedy=data
"""

from __future__ import annotations

import argparse
import json

import jax
import jax.numpy as jnp
import numpy as np
from scipy.stats import spearmanr

from lazyq_jax.local_model import fit_local_linear
from lazyq_jax.run import load_run
from lazyq_jax.targets import bootstrap_table
from lazyq_jax.tasks.cube.env import OBS

BANDS = (1, 3, 10, 30, 100, 300, 1000)


def pairs(data, n: int, max_h: int, rng: np.random.Generator):
    """``(rows, h)``: rows of the first seed whose trajectory goes on at least ``h`` steps."""
    traj_last = np.asarray(data.traj_last)
    size = traj_last.shape[0]
    rows = rng.integers(0, size, 4 * n)
    h = np.exp(rng.uniform(0, np.log(max_h), 4 * n)).astype(int)
    ok = rows + h - 1 <= traj_last[rows]
    return rows[ok][:n], h[ok][:n]


def bootstrap_spearman(v, h, rng, reps=200):
    rho = spearmanr(v, -h).statistic
    idx = rng.integers(0, len(v), (reps, len(v)))
    draws = [spearmanr(v[i], -h[i]).statistic for i in idx]
    return float(rho), [float(np.quantile(draws, 0.025)), float(np.quantile(draws, 0.975))]


def v_fn_of(loaded):
    """The trained ``V(s, g)`` of a loaded run's first seed."""
    return loaded.agent.value_fn(loaded.state())


def fit_r2(neighbourhoods, table) -> tuple[float, float]:
    """Mean R^2 of Eq. (6)'s fits ``y_j ~ alpha + beta . a_j`` over the sampled
    neighbourhoods ``idx [R, k]`` of ``data``, ``y`` the value table ``[N]``; and ``n_a / (k - 1)``."""
    data, idx = neighbourhoods
    y = np.asarray(table)[idx]
    a = np.asarray(data.a)[idx]
    alpha, beta = fit_local_linear(jnp.asarray(a), jnp.asarray(y))
    resid = y - np.asarray(alpha)[:, None] - np.einsum("rkn,rn->rk", a, np.asarray(beta))
    sst = np.sum((y - y.mean(1, keepdims=True)) ** 2, 1)
    ok = sst > 0
    r2 = 1 - np.sum(resid ** 2, 1)[ok] / sst[ok]
    return float(np.mean(r2)), a.shape[-1] / (idx.shape[1] - 1)


def composition(neighbourhoods, traj_last, tol: float = 0.1) -> dict:
    """What Eq. (6)'s fits get from lazy Q's neighbourhoods ``idx [R, k]``: medians over them
    of the distinct trajectories among the ``k`` neighbours, the distinct actions (two
    actions the same if they share a cell of a ``tol``-wide grid on every axis of the box), the
    centred action matrix's smallest singular value over ``sqrt(k)`` (the spread of the
    least-spread direction of the neighbours' actions, in action units; 0: no action varies
    that way), and the share of neighbourhoods whose ``[1, a_j]`` design has rank below
    ``n_a + 1`` (Eq. 6 underdetermined)."""
    data, idx = neighbourhoods
    a = np.asarray(data.a)[idx]  # [R, k, n_a]
    trajs = np.asarray(traj_last)[idx]
    cells = np.floor(a / tol).astype(np.int64)
    distinct_traj = [len(np.unique(t)) for t in trajs]
    distinct_a = [len(np.unique(c, axis=0)) for c in cells]
    centred = a - a.mean(1, keepdims=True)
    sv = np.linalg.svd(centred, compute_uv=False)  # [R, min(k, n_a)]
    design = np.concatenate([np.ones(a.shape[:2] + (1,)), a], -1)
    rank = np.linalg.matrix_rank(design)
    return {"k": int(idx.shape[1]), "n_a": int(a.shape[-1]),
            "distinct_trajectories_median": float(np.median(distinct_traj)),
            "distinct_actions_median": float(np.median(distinct_a)), "tol": tol,
            "smallest_action_spread_median": float(np.median(sv[:, -1] / np.sqrt(idx.shape[1]))),
            "largest_action_spread_median": float(np.median(sv[:, 0] / np.sqrt(idx.shape[1]))),
            "rank_deficient_share": float(np.mean(rank < a.shape[-1] + 1))}


def act_with(lazy, table) -> dict:
    """Seed 0's rates of lazy Q's policy (run ``lazy``) with the value table ``[N]``."""
    sd, agent = lazy.data, lazy.agent
    one = lambda tree: jax.tree.map(lambda x: x[:1], tree)
    policy = agent.policies(one(lazy.states), one(sd.stacked), sd.n_valid[:1])
    if policy.value_apply is not None:
        raise SystemExit("--lazy-policy: acting settings that value neighbours per step "
                         "(subgoal_steps, bootstrap_goal='row') call lazy Q's own network; use a table policy")
    policy = policy.replace(values=jnp.asarray(table)[None])
    ev = lazy.task.evaluate(agent.act, policy, lazy.config, [lazy.seeds[0]])
    return lazy.task.seed_rates(ev.per_seed[0])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", nargs="+", required=True, help="RUN_DIR:METHOD (method default lazy)")
    ap.add_argument("--pairs", type=int, default=20000)
    ap.add_argument("--max-h", type=int, default=1000)
    ap.add_argument("--out", default=None, help="write the numbers as JSON here")
    ap.add_argument("--lazy-policy", default=None, metavar="RUN_DIR",
                    help="also act with lazy Q's policy of this run on each run's V")
    ap.add_argument("--fit-rows", type=int, default=20000,
                    help="neighbourhoods whose local fits' R^2 is reported (with --lazy-policy)")
    ap.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                    help="eval.* and lazy Q's acting settings for --lazy-policy")
    args = ap.parse_args()
    out = {}
    lazy = load_run(args.lazy_policy, "lazy", args.set) if args.lazy_policy else None
    neighbourhoods = None
    if lazy is not None:
        first = jax.tree.map(lambda x: x[0], lazy.data.stacked)
        n = int(lazy.data.n_valid[0])
        rows = np.random.default_rng(1).choice(n, min(args.fit_rows, n), replace=False)
        neighbourhoods = (first, np.asarray(lazy.agent.prepare(lazy.seeds[0], first, n, 0).idx)[rows])
        out["neighbourhoods"] = composition(neighbourhoods, first.traj_last)
        c = out["neighbourhoods"]
        print(f"lazy Q's neighbourhoods ({len(rows)}, k = {c['k']}): distinct trajectories {c['distinct_trajectories_median']:.0f}, "
              f"distinct actions (grid {c['tol']}) {c['distinct_actions_median']:.0f}, action spread (median singular value / "
              f"sqrt k) least {c['smallest_action_spread_median']:.3f}, most {c['largest_action_spread_median']:.3f}; "
              f"rank-deficient designs {100 * c['rank_deficient_share']:.1f} %")
    for spec in args.runs:
        run_dir, _, method = spec.partition(":")
        loaded = load_run(run_dir, method or "lazy")
        data = jax.tree.map(lambda x: x[0], loaded.data.stacked)
        rng = np.random.default_rng(0)
        rows, h = pairs(data, args.pairs, args.max_h, rng)
        s = np.asarray(data.s)[rows]
        g = np.asarray(data.s_next)[rows + h - 1]  # the state h steps after s
        v_fn = jax.jit(v_fn_of(loaded))
        v = np.concatenate([np.asarray(v_fn(jnp.asarray(s[i:i + 4096]), jnp.asarray(g[i:i + 4096])))
                            for i in range(0, len(s), 4096)]).reshape(-1)
        gamma = loaded.config.train.gamma
        cube = OBS["cube_pos"]
        moved = np.linalg.norm(g[:, cube] - s[:, cube], axis=1) > 0.4  # > 4 cm, observation units
        band = np.digitize(h, BANDS)
        by_h = [{"h": f"[{BANDS[b - 1]}, {BANDS[b] if b < len(BANDS) else args.max_h})",
                 "pairs": int(np.sum(band == b)), "V": float(np.mean(v[band == b])),
                 "V*(h)": float(np.mean(-(1 - gamma ** h[band == b]) / (1 - gamma)))}
                for b in range(1, len(BANDS) + 1) if np.any(band == b)]
        rho_all = bootstrap_spearman(v, h, rng)
        rho_moved = bootstrap_spearman(v[moved], h[moved], rng)
        out[spec] = {"by_h": by_h, "spearman_all": rho_all, "spearman_cube_moved": rho_moved,
                     "cube_moved_pairs": int(moved.sum())}
        print(f"\n{spec}: Spearman(V, -h) all {rho_all[0]:.3f} [{rho_all[1][0]:.3f}, {rho_all[1][1]:.3f}], "
              f"cube moved > 4 cm ({int(moved.sum())} pairs) {rho_moved[0]:.3f} "
              f"[{rho_moved[1][0]:.3f}, {rho_moved[1][1]:.3f}]")
        print("| h | pairs | mean V | V*(h) |\n|---|---|---|---|")
        for r in by_h:
            print(f"| {r['h']} | {r['pairs']} | {r['V']:.1f} | {r['V*(h)']:.1f} |")
        if lazy is not None:
            # y_j = r_j + gamma (1 - done_j) V(s'_j, g_j) of lazy Q's first seed, once for both uses
            table = bootstrap_table(v_fn, neighbourhoods[0], lazy.config.train.gamma)
            r2, noise = fit_r2(neighbourhoods, table)
            out[spec]["fit_r2"] = {"mean": r2, "noise_level": noise}
            print(f"local fits over lazy Q's neighbourhoods: mean R^2 {r2:.3f} (pure noise: {noise:.3f})")
            out[spec]["lazy_policy"] = act_with(lazy, table)
            rates = out[spec]["lazy_policy"]
            print(f"lazy Q's policy of {args.lazy_policy} on this V: success {100 * rates['success_rate']:.1f} % ("
                  + ", ".join(f"task {i} {100 * rates[f'task{i}']:.0f} %" for i in range(1, 6)) + ")")
    if args.out:
        with open(args.out, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
