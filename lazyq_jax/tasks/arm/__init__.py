"""The paper's motivation (§II-C, §IV-A): a planar 3-link arm pushing the disk in joint space.

State: the joint angles ``q`` (``arm``, ``d_s = 3``; the disk at the origin) or ``(q,
1.2 disk_xy)`` (``arm-long``, ``d_s = 5``; the disk anywhere); action: a joint move of
0.12 rad (``n_a = 3``); goal: the push direction angle; reward: Eq. (15) of the disk's
move, in the push task's world.  Protocol A in joint space, and with the disk in the
state the long-horizon task; online rounds (preset ``online``).
"""

from __future__ import annotations

import dataclasses
import functools
from pathlib import Path
from typing import Callable, Sequence

import jax
import jax.numpy as jnp
from jax.sharding import Mesh

from lazyq_jax.agents.base import Act, Problem
from lazyq_jax.config import Config
from lazyq_jax.tasks.arm import plots
from lazyq_jax.tasks.arm.config import ArmCollectConfig, ArmEvalConfig, check, presets
from lazyq_jax.tasks.arm.env import ArmConfig, ArmEnv, ArmState, fingertip_xy, sample_arm_start
from lazyq_jax.tasks.arm.episodes import (collect_arm, disk_at_origin, explore_round,
                                          fingertip_features, protocol_a, protocol_b,
                                          scripted_arm_policy, state_scale)
from lazyq_jax.tasks.base import Evaluation, Task, run_protocol, seed_acts
from lazyq_jax.tasks.push import PushTask
from lazyq_jax.tasks.push.collect import dataset_summary
from lazyq_jax.tasks.push.plots import fig4_outcomes, fig5_trajectories
from lazyq_jax.tasks.push.protocols import (direction_seed_rates, eval_keys, summarize_a,
                                            summarize_b)
from lazyq_jax.types import Transitions

__all__ = ["ArmCollectConfig", "ArmConfig", "ArmEnv", "ArmEvalConfig", "ArmState", "ArmTask",
           "collect_arm", "fingertip_xy", "sample_arm_start"]


class ArmTask(Task):
    """``arm`` (``disk_range=None``) or ``arm-long`` (the disk anywhere within
    ``disk_range``); the data's fingertip starts within ``start_range`` of the disk."""

    collect_config = ArmCollectConfig
    eval_config = ArmEvalConfig
    directions = True
    online = True

    def __init__(self, name: str, disk_range: float | None, start_range: float = 1.0):
        self.name = name
        self.presets = presets(disk_range, start_range)
        self.summary = ("a 3-link arm pushing the disk in joint space, the disk at the origin (d_s = 3)"
                        if disk_range is None else
                        "the arm with the disk anywhere, in the state (d_s = 5); long-horizon task")
        rates = PushTask.rates
        self.rates = rates if disk_range is not None else rates[:3]

    def check(self, config: Config) -> None:
        super().check(config)
        check(config)

    def feature_maps(self, config: Config) -> dict:
        return {"state": None,
                "fingertip": fingertip_features(config.collect, config.neighbours.feature_weight)}

    def problem(self, config: Config) -> Problem:
        return Problem(action_length=config.collect.arm.action_length, action_set="ball",
                       state_scale=state_scale(config.collect), features=self.features(config))

    def collect(self, key, config: Config, *, mesh: Mesh | None = None, progress: bool = True
                ) -> Transitions:
        return collect_arm(key, config.collect, mesh=mesh, progress=progress)

    def data_summary(self, data: Transitions, config: Config) -> dict:
        return dataset_summary(data, config.collect.n_goals)

    data_table = PushTask.data_table

    def rows_per_move(self, config: Config) -> int:
        return config.collect.n_goals

    def explore(self, act: Act, key, config: Config) -> dict:
        return explore_round(act, key, config)

    def evaluate(self, act_of, policies, config: Config, seeds: Sequence[int], *,
                 quick: bool = False) -> Evaluation:
        cfg = config.eval
        if quick:
            cfg = dataclasses.replace(cfg, episodes_per_direction=config.online.eval_episodes)
        long = config.collect.disk_in_state and not quick
        program_a, program_b = _programs(config.collect, cfg, long)
        acts = seed_acts(act_of)
        keys = [eval_keys(int(s) + cfg.seed) for s in seeds]
        k_a, k_b = (jnp.stack([k[i] for k in keys]) for i in (0, 1))
        rollouts = {"protocol_a": run_protocol(program_a, acts, policies, k_a)}
        if long:
            rollouts["protocol_b"] = run_protocol(program_b, acts, policies, k_b)
        per_seed = []
        for i, seed in enumerate(seeds):
            pick = lambda tree: jax.tree.map(lambda x: x[i], tree)
            result = {"seed": int(seed), "eval_seed": int(seed) + cfg.seed,
                      "protocol_a": summarize_a(pick(rollouts["protocol_a"]), cfg.n_directions,
                                                cfg.episodes_per_direction)}
            if long:
                result["protocol_b"] = summarize_b(pick(rollouts["protocol_b"]))
            per_seed.append(result)
        return Evaluation(per_seed, rollouts)

    def seed_rates(self, result: dict) -> dict:
        return direction_seed_rates(result)

    def scripted(self, config: Config) -> Act:
        return scripted_arm_policy(config.collect)

    def figures(self, out_dir: Path, result: dict, rollouts: dict, config: Config,
                value_fn: Callable | None = None) -> list[Path]:
        out_dir.mkdir(parents=True, exist_ok=True)
        arm = config.collect.arm
        paths = [out_dir / "fig4_outcomes.png", out_dir / "arm_trajectories.png"]
        fig4_outcomes(result, paths[0])
        plots.arm_trajectories(rollouts["protocol_a"], arm, config.eval, paths[1])
        if value_fn is not None:
            paths.append(out_dir / "arm_value.png")
            plots.arm_value(value_fn, arm, paths[-1], state_of=disk_at_origin(config.collect))
        if "protocol_b" in rollouts:
            paths.append(out_dir / "fig5_long_horizon.png")
            rb = rollouts["protocol_b"]
            fig5_trajectories(rb, rb.ctx, result, arm.push.table_half_size,
                              config.eval.success_radius, paths[-1])
        return paths

    def animate(self, path: Path, rollouts: dict, config: Config) -> Path:
        return plots.animate(path, rollouts, config)


@functools.lru_cache(maxsize=16)
def _programs(collect: ArmCollectConfig, cfg: ArmEvalConfig, long: bool):
    """The protocols' compiled physics, kept per config and shared by every method."""
    env = ArmEnv(collect.arm)  # float32 physics, as in every evaluation
    return protocol_a(env, cfg, collect), protocol_b(env, cfg, collect) if long else None
