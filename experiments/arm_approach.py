"""Where the arm's "not pushed" episodes fail: the approach or the contact.  Re-runs protocol A
(the run's own evaluation keys, so the outcomes are those of its ``eval.json``) for lazy Q of
a trained arm run and for the task's scripted controller, and reports per outcome the
fingertip's gap to contact (``|fingertip - disk| - contact distance``) at the start, its
smallest value over the episode and at the end, and the moves without an action (lazy Q:
no neighbourhood within ``max_level``).  Trains nothing.

    .venv/bin/python experiments/arm_approach.py runs/arm_levers/arm-long/online_fingertip_offsets
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from lazyq_jax.run import load_run
from lazyq_jax.tasks.base import CORRECT, NOT_PUSHED, WRONG

NAMES = {CORRECT: "correct", WRONG: "wrong direction", NOT_PUSHED: "not pushed"}
NEAR = 0.1  # one fingertip step on average (docs/arm.md)


def gaps(rollouts, contact: float) -> np.ndarray:
    """``[S, T + 1, B]`` gap between fingertip and disk edge-to-contact."""
    return np.linalg.norm(rollouts.agent - rollouts.obj, axis=-1) - contact


def summarise(rollouts, contact: float) -> dict:
    gap = gaps(rollouts, contact)
    steps = rollouts.steps  # [S, B]
    last = np.take_along_axis(gap, steps[:, None, :], axis=1)[:, 0]  # the gap after the final move
    # the smallest gap up to the final move (the records repeat the final state after it)
    smallest = gap.min(axis=1)
    rows = {}
    for code, name in NAMES.items():
        m = rollouts.outcome == code
        if not m.any():
            continue
        rows[name] = {"episodes": int(m.sum()), "start_gap": float(gap[:, 0][m].mean()),
                      "smallest_gap": float(smallest[m].mean()), "final_gap": float(last[m].mean()),
                      "came_within_step": float((smallest[m] < NEAR).mean()),
                      "idle_moves": float(rollouts.idle[m].mean()), "moves": float(steps[m].mean())}
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run_dir", type=Path)
    ap.add_argument("--out", type=Path, help="JSON file (default: RUN_DIR/approach.json)")
    args = ap.parse_args()
    loaded = load_run(args.run_dir, "lazy")
    config, task = loaded.config, loaded.task
    contact = config.collect.arm.push.contact_distance
    table = {}
    policies = loaded.agent.policies(loaded.states, loaded.data.stacked, loaded.data.n_valid)
    ev = task.evaluate(loaded.agent.act, policies, config, loaded.seeds)
    table["lazy"] = summarise(ev.rollouts["protocol_a"], contact)
    scripted = task.scripted(config)
    dummy = jnp.zeros((len(loaded.seeds),))
    ev = task.evaluate(lambda _: scripted, dummy, config, loaded.seeds)
    table["scripted"] = summarise(ev.rollouts["protocol_a"], contact)
    out = args.out or args.run_dir / "approach.json"
    out.write_text(json.dumps(table, indent=1))
    print(f"{args.run_dir}, seeds {list(loaded.seeds)}: protocol A, gap = |fingertip - disk| - "
          f"{contact:g} (contact); means per outcome")
    print("| method | outcome | episodes | start gap | smallest gap | final gap "
          f"| came within {NEAR:g} | moves | moves without action |")
    print("|---|---|---|---|---|---|---|---|---|")
    for method, rows in table.items():
        for name, r in rows.items():
            print(f"| {method} | {name} | {r['episodes']} | {r['start_gap']:.3f} | {r['smallest_gap']:.3f} "
                  f"| {r['final_gap']:.3f} | {r['came_within_step']:.1%} | {r['moves']:.1f} "
                  f"| {r['idle_moves']:.1f} |")


if __name__ == "__main__":
    main()
