"""Lazy Q on the arm (joint-space pushing), end to end for one seed, with diagnostics.

The second task of the general core: states are the arm's joint angles ``q`` (d_s = 3),
actions joint moves of norm 0.12 rad (n_a = 3), goals the push direction (an angle).
Pipeline: the §V-A-3 dataset in joint space (:func:`lazyq_jax.arm_task.collect_arm`),
neighbourhoods through ``find_neighbours`` (the general search), the paper preset's
training (10 x 10 epochs) with per-joint input scaling, the lazy policy (Eq. 9, a
jittable scan query per step) and protocol A (:func:`lazyq_jax.arm_task.arm_protocol_a`).

What makes joint space harder is measured on the way: the neighbourhood levels the
search needs (radius growth), the fraction of clipped targets, the data's coverage
(+1 rewards per goal octant).

    .venv/bin/python experiments/arm_run.py [--seed 0] [--radius-s 0.12] [--starts 5000]
        [--episodes 10] [--out runs/arm_run]

Writes ``<out>/results.json`` and ``<out>/outcomes.png`` (one seed: label it so).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax
import numpy as np

import lazyq_jax as lq
from lazyq_jax import plots
from lazyq_jax.arm_task import arm_protocol_a, collect_arm
from lazyq_jax.data import dataset_summary
from lazyq_jax.env.arm import ArmConfig, ArmEnv
from lazyq_jax.evaluate import policy_act, summarize_a


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--radius-s", type=float, default=0.12, help="joint-space radius (rad)")
    ap.add_argument("--radius-g", type=float, default=0.1)
    ap.add_argument("--k", type=int, default=20)
    ap.add_argument("--starts", type=int, default=5000)
    ap.add_argument("--cycles", type=int, default=10)
    ap.add_argument("--episodes", type=int, default=10, help="protocol A episodes per direction")
    ap.add_argument("--max-steps", type=int, default=50)
    ap.add_argument("--out", type=Path, default=Path("runs/arm_run"))
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    key = jax.random.PRNGKey(args.seed)
    k_data, k_nb, k_train, k_eval, k_pol = jax.random.split(key, 5)
    arm = ArmConfig()
    timings, out = {}, {"seed": args.seed, "args": {k: str(v) for k, v in vars(args).items()}}

    t = time.perf_counter()
    collect_cfg = lq.CollectConfig(n_starts=args.starts)
    data = collect_arm(k_data, arm, collect_cfg, progress=False)
    timings["collect_s"] = time.perf_counter() - t
    summary = dataset_summary(data, collect_cfg.n_goals)
    out["dataset"] = {"rows": int(data.s.shape[0]), "summary": summary}
    print(f"dataset: {data.s.shape[0]:,} rows ({timings['collect_s']:.1f} s)", flush=True)

    t = time.perf_counter()
    nb = lq.find_neighbours(k_nb, data.s, data.g, data.s, data.g, k=args.k, radius_s=args.radius_s,
                            radius_g=args.radius_g)
    timings["neighbours_s"] = time.perf_counter() - t
    level = np.asarray(nb.level)
    out["levels"] = {"mean": float(level.mean()), "median": float(np.median(level)),
                     "p90": float(np.percentile(level, 90)), "max": int(level.max()),
                     "histogram": np.bincount(level).tolist()}
    print(f"neighbours: levels mean {level.mean():.2f}, median {np.median(level):.0f}, max {level.max()} "
          f"({timings['neighbours_s']:.1f} s)", flush=True)

    t = time.perf_counter()
    scale = (np.asarray(arm.joint_upper) - np.asarray(arm.joint_lower)) / 2
    train_cfg = lq.TrainConfig(cycles=args.cycles)
    trainer = lq.make_train(train_cfg, arm.action_length, state_dim=3, goal="angle",
                            state_scale=tuple(float(x) for x in scale))
    state, metrics = jax.block_until_ready(jax.jit(trainer.train)(k_train, data, nb.idx))
    timings["train_s"] = time.perf_counter() - t
    out["training"] = {k: np.asarray(v).round(5).tolist() for k, v in metrics.items()
                       if k in ("loss", "clip_fraction", "target_mean")}
    print(f"training: final loss {np.asarray(metrics['loss'])[-1]:.4g}, clipped "
          f"{np.asarray(metrics['clip_fraction'])[-1]:.1%} ({timings['train_s']:.1f} s)", flush=True)

    t = time.perf_counter()
    policy = lq.make_lazy_policy(trainer.value_fn(state), data, gamma=train_cfg.gamma,
                                 action_length=arm.action_length, k=args.k, radius_s=args.radius_s,
                                 radius_g=args.radius_g, max_level=max(16, int(level.max()) + 4))
    eval_cfg = lq.EvalConfig(episodes_per_direction=args.episodes, max_steps=args.max_steps)
    env = ArmEnv(arm)
    rollouts, _ = arm_protocol_a(env, policy_act(policy), k_eval, eval_cfg)
    result = summarize_a(rollouts, eval_cfg)
    timings["protocol_a_s"] = time.perf_counter() - t
    out["protocol_a"] = result
    out["timings"] = {k: round(v, 1) for k, v in timings.items()}
    (args.out / "results.json").write_text(json.dumps(out, indent=1))
    plots.fig4_outcomes({"protocol_a": result}, args.out / "outcomes.png")
    rows = result["per_goal"]
    print("protocol A (one seed): axis correct {:.1%}, all 16 correct {:.1%}; per direction "
          "(correct/wrong/not pushed): {}".format(
              result["axis_correct_rate"], result["overall_correct_rate"],
              ", ".join(f"{np.degrees(r['goal']):.0f}°: {r['correct']}/{r['wrong']}/{r['not_pushed']}"
                        for r in rows)))
    print(json.dumps(out["timings"]))


if __name__ == "__main__":
    main()
