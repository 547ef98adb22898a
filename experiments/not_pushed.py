"""Why do protocol-A episodes end "not pushed"?  Reruns protocol A of a finished run
(deterministic, same seed) and relates those episodes to policy steps that found no
neighbourhood (the finger outside the data).

    .venv/bin/python experiments/not_pushed.py [--run-dir runs/paper]
"""

from __future__ import annotations

import argparse

import jax
import numpy as np

from lazyq_jax.env import PushEnv
from lazyq_jax.evaluate import NOT_PUSHED, eval_keys, load_run, policy_act, protocol_a, run_policy


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--run-dir", default="runs/paper")
    args = ap.parse_args()
    config, state, trainer, data = load_run(args.run_dir)
    cfg = config.eval
    policy = run_policy(config, trainer.value_fn(state), data, cfg.max_level)
    k_a, _ = eval_keys(cfg)  # as evaluate_run does
    env = PushEnv(config.collect.push)
    r = jax.device_get(jax.jit(lambda p, k: protocol_a(env, policy_act(p), k, cfg))(policy, k_a))
    stuck = r.outcome == NOT_PUSHED
    print(f"not pushed: {stuck.sum()} of {stuck.size} episodes; with steps lacking a neighbourhood: "
          f"{(stuck & (r.lost > 0)).sum()} (holding {r.lost[stuck].sum()} of {r.lost.sum()} such steps)")
    print("their start distance from the disk:", np.linalg.norm(r.finger[0][stuck], axis=1).round(2))
    print("their final max(|x|, |y|) of the finger:", np.abs(r.finger[-1][stuck]).max(1).round(2))


if __name__ == "__main__":
    main()
