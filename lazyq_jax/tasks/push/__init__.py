"""The paper's task (§V-A-1): a spherical finger pushes a disk on a table in a given direction.

State: the finger relative to the disk (``d_s = 2``); action: a finger move of length 0.1
(the circle); goal: the push direction angle; reward: Eq. (15).  Two worlds (presets
``paper``: Coulomb friction per table axis; ``forgiving``: quadratic drag), the
paper's random dataset (§V-A-3), its two evaluations (§V-B: goal directions and the
long-horizon task), a scripted controller, and online rounds (preset ``online``).
"""

from __future__ import annotations

import dataclasses
import functools
from pathlib import Path
from typing import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh

from lazyq_jax.agents.base import Act, Problem
from lazyq_jax.config import Config
from lazyq_jax.tasks.base import Evaluation, Task, run_protocol, seed_acts
from lazyq_jax.tasks.push import plots
from lazyq_jax.tasks.push.collect import collect, dataset_summary
from lazyq_jax.tasks.push.config import FORGIVING_PUSH, PRESETS, CollectConfig, EvalConfig, PushConfig, check
from lazyq_jax.tasks.push.env import PushEnv, PushState
from lazyq_jax.tasks.push.explore import explore_round
from lazyq_jax.tasks.push.protocols import (direction_seed_rates, eval_keys, protocol_a, protocol_b,
                                            summarize_a, summarize_b)
from lazyq_jax.tasks.push.reward import push_reward
from lazyq_jax.tasks.push.scripted import scripted_push_policy
from lazyq_jax.types import Transitions

__all__ = ["FORGIVING_PUSH", "CollectConfig", "EvalConfig", "PushConfig", "PushEnv", "PushState",
           "PushTask", "push_reward", "scripted_push_policy"]

# Probe points (s, g) whose values lazy Q logs every cycle: the finger behind the disk for
# goals 0 and pi/2 (should become valuable), the same spots for the opposite goals, and a
# finger far from the disk.
PROBES = (((-0.35, 0.0), (0.0, -0.35), (-0.35, 0.0), (0.0, -0.35), (0.9, 0.9)),
          (0.0, np.pi / 2, np.pi, -np.pi / 2, 0.0))

RATES = (("axis_correct_rate", "axis goals correct"), ("diagonal_correct_rate", "diagonal goals correct"),
         ("overall_correct_rate", "all goals correct"), ("long_horizon_success_rate", "long horizon reached"))


class PushTask(Task):
    name = "push"
    summary = "the paper's finger pushing a disk (d_s = 2, angle goals)"
    collect_config = CollectConfig
    eval_config = EvalConfig
    presets = PRESETS
    rates = RATES
    directions = True
    online = True

    def check(self, config: Config) -> None:
        super().check(config)
        check(config)

    def search_bounds(self, config: Config) -> tuple[float, float, float, float]:
        """Fixed bounds of the neighbour grid covering every state of the data (finger starts
        in ``[-R, R]^2`` plus ``moves_per_start - 1`` moves) and of the online rounds'
        episodes: the training search's grid, hence its neighbour samples, are the same for
        every dataset of a config (a study's seeds, the online rounds), and the compiled
        passes are shared (the policy's index chooses its own layout)."""
        c, o = config.collect, config.online
        step = c.push.action_length
        r = c.start_range + (c.moves_per_start - 1) * step
        if o.rounds:
            r = max(r, c.explore_range + o.max_steps * step)
        r += 1e-3
        return -r, -r, r, r

    def problem(self, config: Config) -> Problem:
        probes = tuple(np.asarray(x, np.float32) for x in PROBES)
        return Problem(action_length=config.collect.push.action_length, action_set="ball",
                       state_scale=config.collect.start_range, probes=probes,
                       search_bounds=self.search_bounds(config), features=self.features(config))

    def collect(self, key, config: Config, *, mesh: Mesh | None = None, progress: bool = True
                ) -> Transitions:
        return collect(key, config.collect, mesh=mesh, progress=progress)

    def data_summary(self, data: Transitions, config: Config) -> dict:
        return dataset_summary(data, config.collect.n_goals)

    def data_table(self, summaries: Sequence[dict]) -> dict:
        """Positive rewards per goal octant, per seed and as mean over the seeds."""
        counts = np.array([[o["positive"] for o in s["reward_by_goal_octant"]] for s in summaries])
        axis, diag = counts[:, 0::2], counts[:, 1::2]
        worst = diag.max(axis=1) / np.maximum(axis.min(axis=1), 1)
        return {"positives_by_octant": {"centre_deg": [45 * i for i in range(8)],
                                        "per_seed": counts.tolist(),
                                        "mean": counts.mean(axis=0).round(1).tolist()},
                "moves_that_moved_disk": [s["moves_that_moved_disk"] for s in summaries],
                "rows": [s["rows"] for s in summaries],
                "diagonal_to_axis_ratio_of_means": float(diag.mean(axis=0).max()
                                                         / max(axis.mean(axis=0).min(), 1e-9)),
                "diagonal_to_axis_ratio_worst_per_seed": worst.round(3).tolist()}

    def rows_per_move(self, config: Config) -> int:
        return config.collect.n_goals

    def explore(self, act: Act, key, config: Config) -> dict:
        return explore_round(act, key, config)

    def evaluate(self, act_of, policies, config: Config, seeds: Sequence[int], *,
                 quick: bool = False) -> Evaluation:
        cfg = config.eval
        if quick:
            cfg = dataclasses.replace(cfg, episodes_per_direction=config.online.eval_episodes)
        program_a, program_b = _programs(config.collect.push, cfg, quick)
        acts = seed_acts(act_of)
        keys = [eval_keys(int(s) + cfg.seed) for s in seeds]
        k_a, k_b = (jnp.stack([k[i] for k in keys]) for i in (0, 1))
        rollouts = {"protocol_a": run_protocol(program_a, acts, policies, k_a)}
        if program_b is not None:
            rollouts["protocol_b"] = run_protocol(program_b, acts, policies, k_b)
        per_seed = []
        for i, seed in enumerate(seeds):
            pick = lambda tree: jax.tree.map(lambda x: x[i], tree)
            result = {"seed": int(seed), "eval_seed": int(seed) + cfg.seed,
                      "protocol_a": summarize_a(pick(rollouts["protocol_a"]), cfg.n_directions,
                                                cfg.episodes_per_direction)}
            if program_b is not None:
                result["protocol_b"] = summarize_b(pick(rollouts["protocol_b"]))
            per_seed.append(result)
        return Evaluation(per_seed, rollouts)

    def seed_rates(self, result: dict) -> dict:
        return direction_seed_rates(result)

    def scripted(self, config: Config) -> Act:
        return scripted_push_policy(config.collect.push)

    def figures(self, out_dir: Path, result: dict, rollouts: dict, config: Config,
                value_fn: Callable | None = None) -> list[Path]:
        out_dir.mkdir(parents=True, exist_ok=True)
        paths = []
        if value_fn is not None:
            paths.append(out_dir / "fig3_value.png")
            plots.fig3_value(value_fn, config, paths[-1])
        paths.append(out_dir / "fig4_outcomes.png")
        plots.fig4_outcomes(result, paths[-1])
        if "protocol_b" in rollouts:
            paths.append(out_dir / "fig5_long_horizon.png")
            rb = rollouts["protocol_b"]
            plots.fig5_trajectories(rb, rb.ctx, result, config.collect.push.table_half_size,
                                    config.eval.success_radius, paths[-1])
        return paths

    def animate(self, path: Path, rollouts: dict, config: Config) -> Path:
        return plots.animate(path, rollouts, config)


@functools.lru_cache(maxsize=16)
def _programs(push: PushConfig, cfg: EvalConfig, quick: bool):
    """The protocols' compiled physics, kept per world and evaluation config and shared by
    every method: evaluating again (another method, an online round) compiles only the
    method's policy."""
    env = PushEnv(push)  # float32 physics, as in every evaluation
    return protocol_a(env, cfg), None if quick else protocol_b(env, cfg)
