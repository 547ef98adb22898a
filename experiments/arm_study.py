"""Lazy Q on the arm over several seeds: mean and 95 % CI of protocol A (and of the
long-horizon task for ``--task arm-long``), with what makes joint space hard.

Each seed is a whole ``train --task ...`` run (:func:`lazyq_jax.arm_task.fit_arm`:
its own dataset, neighbourhoods, training, evaluation) in ``<out>/seeds/<seed>``; the
seeds run one after another and a study that was stopped continues where it stopped
(finished seeds are read back, an unfinished one resumes from its newest checkpoint).

    .venv/bin/python experiments/arm_study.py --task arm-long --seeds 3 \\
        [--preset paper] [--set eval.long_rollouts=50 ...] [--out runs/arm_long_study]

A reference that learns nothing runs beside each seed: uniformly random joint moves
(``random_*`` entries), evaluated with ``eval.seed`` set to the seed (starts from the
same distributions as the lazy runs', other draws per seed).

Writes ``<out>/results.json`` (per seed and aggregated) and ``<out>/summary.md``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from lazyq_jax.arm_task import ARM_TASKS, ArmTask, arm_protocol_a, arm_protocol_b, fit_arm
from lazyq_jax.config import Config, override, preset
from lazyq_jax.env.arm import ArmConfig, ArmEnv
from lazyq_jax.evaluate import CORRECT, direction_rates, eval_keys, summarize_a
from lazyq_jax.parallel import enable_compilation_cache
from lazyq_jax.stats import format_ci, t_interval


def seed_record(run: Path) -> dict:
    """What one finished seed's run directory says."""
    results = json.loads((run / "eval" / "results.json").read_text())
    metrics = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    levels = json.loads((run / "neighbours.json").read_text())
    hist = np.asarray(levels["histogram"], float)
    record = {**direction_rates(results["protocol_a"]),
              "level_mean": levels["mean"], "level0_fraction": float(hist[0] / hist.sum()),
              "clip_fraction": metrics[-1]["clip_fraction"],
              "summary": json.loads((run / "dataset_summary.json").read_text()),
              "timings": results["timings"]}
    if "protocol_b" in results:
        b = results["protocol_b"]
        record["long_success_rate"] = b["successes"] / b["rollouts"]
        record["long"] = b
    return record


def random_moves(key, s, g):
    """Uniformly random joint-move directions (the env scales them to ``action_length``)."""
    return jax.random.normal(key, (s.shape[0], 3)), jnp.ones(s.shape[0], bool)


def random_reference(config: Config, task: ArmTask) -> dict:
    """Protocol A (and the long-horizon task) of :func:`random_moves` with the evaluation
    keys of ``eval.seed = config.seed``: what the tasks give to a policy that learns nothing."""
    env = ArmEnv(ArmConfig(push=config.collect.push))
    key_a, key_b = eval_keys(dataclasses.replace(config.eval, seed=config.seed))
    rollouts, _ = arm_protocol_a(env, random_moves, key_a, config.eval, task)
    rates = direction_rates(summarize_a(rollouts, config.eval))
    out = {f"random_{k}": v for k, v in rates.items()}
    if task.disk_in_state:
        ro, _, _ = arm_protocol_b(env, random_moves, key_b, config.eval, task)
        out["random_long_success_rate"] = float(np.mean(np.asarray(ro.outcome) == CORRECT))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--task", choices=sorted(ARM_TASKS), default="arm-long")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--preset", default="paper")
    ap.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                    help="config override as for the CLI, e.g. eval.long_rollouts=50")
    ap.add_argument("--out", type=Path, default=None, help="default runs/<task>_study")
    args = ap.parse_args()
    enable_compilation_cache()
    out = args.out or Path("runs") / f"{args.task.replace('-', '_')}_study"
    base = override(preset(args.preset), args.set)
    records = {}
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        run = out / "seeds" / str(seed)
        if not (run / "eval" / "results.json").exists():
            print(f"--- seed {seed} -> {run}", flush=True)
            fit_arm(override(base, [f"seed={seed}"]), run, task=ARM_TASKS[args.task], resume=True,
                    progress=False)
        records[seed] = seed_record(run)
        records[seed].update(random_reference(override(base, [f"seed={seed}"]), ARM_TASKS[args.task]))
    names = ["axis_correct_rate", "diagonal_correct_rate", "overall_correct_rate", "level_mean",
             "level0_fraction", "clip_fraction"]
    if all("long_success_rate" in r for r in records.values()):
        names.append("long_success_rate")
    names += [n for n in records[min(records)] if n.startswith("random_")]
    # e.g. no diagonal goals with fewer than 8 directions
    names = [n for n in names if all(np.isfinite(r[n]) for r in records.values())]
    aggregate = {n: t_interval([r[n] for r in records.values()],
                               bounds=None if n == "level_mean" else (0.0, 1.0)) for n in names}
    (out / "results.json").write_text(json.dumps(
        {"task": args.task, "preset": args.preset, "set": args.set, "seeds": sorted(records),
         "aggregate": aggregate, "per_seed": records}, indent=1))
    lines = [f"# {args.task}: {len(records)} seeds ({args.preset} preset"
             f"{', ' + ', '.join(args.set) if args.set else ''}), mean [95 % CI]", ""]
    for n in names:
        text = format_ci(aggregate[n], percent=n != "level_mean")
        lines.append(f"- {n}: {text}  (per seed: "
                     + ", ".join(f"{r[n]:.3g}" for r in records.values()) + ")")
    (out / "summary.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
