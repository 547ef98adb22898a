"""How high can a policy get on ``arm``'s protocol A?  The scripted controller improved by
rollouts in the true simulator: a reference above the scripted one, to tell the task's own
limits (the 90 degree reach, the paper world's friction per axis) from lazy Q's.

At every step the policy tries ``--candidates`` first moves: the scripted controller's own
move (first) and joint moves of the usual length in random directions.  Each candidate is
simulated (the task's MJX physics, float32 as in every evaluation), then the scripted
controller acts for ``--horizon`` more moves; a candidate scores +1 if the first push that
moves the disk goes the goal's way (protocol A's outcome), -1 if it goes another way, 0 if
none moves the disk within the horizon.  The best score wins; ties go to the earliest
candidate, so the scripted move is kept unless a candidate does better (Bertsekas' rollout
policy: with a horizon that covers the rest of an episode it is never worse than the
controller it improves).  It knows the physics exactly and learns nothing: an upper
reference, not a method.  The same episodes (protocol A's keys of each seed) as every run of
``arm``; trains nothing, needs no data.

    .venv/bin/python experiments/arm_ceiling.py --seeds 5 --candidates 12 --horizon 8
    .venv/bin/python experiments/arm_ceiling.py --seeds 5 --candidates 24 --horizon 16 \\
        --set eval.n_directions=4 --out runs/arm_ceiling_axis.json     # the axis goals only
    .venv/bin/python experiments/arm_ceiling.py --report runs/arm_ceiling.json
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import jax
import jax.numpy as jnp
from _common import rate_keys, rates_table  # the script's own folder is on sys.path

from lazyq_jax import tasks
from lazyq_jax.config import Config, override
from lazyq_jax.tasks.arm.env import ArmEnv, ArmState
from lazyq_jax.tasks.arm.episodes import scripted_arm_policy
from lazyq_jax.tasks.base import CORRECT
from lazyq_jax.tasks.push.protocols import direction_outcome


def rollout_policy(config: Config, candidates: int, horizon: int):
    """``act(key, s [B, 3], g [B]) -> dq [B, 3]`` for ``arm`` (the disk at the origin, the
    state the joint angles): the rollout-improved scripted controller (module docstring)."""
    collect = config.collect
    if collect.disk_in_state:
        raise ValueError("arm_ceiling: only the 'arm' task (the disk at the origin, not in the "
                         "state); arm-long's long-horizon task needs another score")
    arm = collect.arm
    env = ArmEnv(arm)
    base = scripted_arm_policy(collect)
    outcome = direction_outcome(arm.push.cos_threshold, arm.push.move_threshold)
    step = jax.vmap(env.step)

    def score(q, disk, g, first):
        """+1 / -1 / 0 of ``first`` then ``horizon`` controller moves, all batched [n]."""
        state, delta = step(ArmState(q, disk), first)
        kind, ended = outcome(delta, g, None)
        result = jnp.where(ended, jnp.where(kind == CORRECT, 1, -1), 0)

        def move(carry, _):
            state, result, done = carry
            dq = base(jax.random.PRNGKey(0), state.q, g)
            new, delta = step(state, dq)
            kind, ends = outcome(delta, g, None)
            live = ~done
            result = jnp.where(live & ends, jnp.where(kind == CORRECT, 1, -1), result)
            state = jax.tree.map(lambda n, o: jnp.where(live.reshape((-1,) + (1,) * (n.ndim - 1)), n, o),
                                 new, state)
            return (state, result, done | ends), None

        (_, result, _), _ = jax.lax.scan(move, (state, result, ended), None, length=horizon)
        return result

    def act(key, s, g):
        b = s.shape[0]
        own = base(key, s, g)[:, None, :]                                    # [B, 1, 3]
        rand = jax.random.normal(key, (b, candidates - 1, 3), s.dtype)
        rand = arm.action_length * rand / jnp.linalg.norm(rand, axis=-1, keepdims=True)
        cand = jnp.concatenate([own, rand], axis=1)                           # [B, M, 3]
        flat = lambda x: jnp.repeat(x, candidates, axis=0)
        scores = score(flat(s[:, :3]), jnp.zeros((b * candidates, 2), s.dtype), flat(g),
                       cand.reshape(-1, 3)).reshape(b, candidates)
        return jnp.take_along_axis(cand, jnp.argmax(scores, axis=1)[:, None, None], axis=1)[:, 0]

    return act


def evaluate(task, config, act, seeds) -> dict:
    """Protocol A of ``seeds`` with ``act``: per-seed rates, outcomes per goal, episodes."""
    t = time.perf_counter()
    ev = task.evaluate(lambda p: act, jnp.zeros((len(seeds), 1)), config, seeds)
    per_goal = {}
    for r in ev.per_seed:
        for row in r["protocol_a"]["per_goal"]:
            cell = per_goal.setdefault(round(math.degrees(row["goal"]), 1), [0, 0, 0])
            for i, kind in enumerate(("correct", "wrong", "not_pushed")):
                cell[i] += int(row[kind])
    ra = ev.rollouts["protocol_a"]  # [seeds, ...]
    return {"rows": [task.seed_rates(r) for r in ev.per_seed], "per_goal": per_goal,
            "seconds": time.perf_counter() - t,
            "episodes": {"goal": ra.ctx.round(4).tolist(), "start": ra.agent[:, 0].round(4).tolist(),
                         "q0": ra.extra[:, 0].round(4).tolist(), "outcome": ra.outcome.tolist(),
                         "steps": ra.steps.tolist()}}


def report(table: dict) -> None:
    """The rates of every policy (mean [95 % CI] over seeds), the rollout's paired gain over the
    scripted controller, the outcomes per goal."""
    rows = {name: t["rows"] for name, t in table.items()}
    first = next(iter(rows.values()))
    keys = [k for k in rate_keys(first[0]) if all(k in rate_keys(r) for r in first)]  # no diagonals with 4 goals
    print(f"\n{len(first)} seeds (protocol A of arm, the runs' episodes); mean [95 % CI]")
    rates_table(rows, keys, head="policy")
    print("\nper goal in degrees: (correct, wrong, not pushed), all seeds")
    for name, t in table.items():
        print(name, {g: tuple(c) for g, c in sorted(t["per_goal"].items(), key=lambda x: float(x[0]))})


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--candidates", type=int, default=12)
    ap.add_argument("--horizon", type=int, default=8)
    ap.add_argument("--set", action="append", default=[], help="config overrides (section.field=value)")
    ap.add_argument("--out", type=Path, default=Path("runs/arm_ceiling.json"))
    ap.add_argument("--report", type=Path, help="print the tables of a saved --out file; run nothing")
    args = ap.parse_args()
    if args.report is not None:
        return report(json.loads(args.report.read_text()))
    if args.candidates < 1 or args.horizon < 0:
        raise SystemExit("--candidates must be >= 1 and --horizon >= 0")
    task = tasks.get("arm")
    config = override(tasks.preset("arm", "paper"), args.set)
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    table = {}
    for name, act in (("scripted", task.scripted(config)),
                      (f"rollout M={args.candidates} H={args.horizon}",
                       rollout_policy(config, args.candidates, args.horizon))):
        table[name] = evaluate(task, config, act, seeds)
        print(f"{name}: {table[name]['seconds']:.0f} s", flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(table, indent=1))
    report(table)


if __name__ == "__main__":
    main()
