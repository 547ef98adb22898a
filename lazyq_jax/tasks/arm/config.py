"""The arm tasks' settings: their data, their evaluation and the presets of ``arm`` (the disk
at the origin, state = joint angles) and ``arm-long`` (the disk anywhere, in the state)."""

from __future__ import annotations

import dataclasses

from lazyq_jax.config import (Config, NeighbourConfig, OnlineConfig, TrainConfig, _check, _counts,
                              _positive)
from lazyq_jax.tasks.arm.env import ArmConfig


@dataclasses.dataclass(frozen=True)
class ArmCollectConfig:
    """Random joint-space pushes (§V-A-3 in joint space) and what the agent sees.

    ``n_starts`` random collision-free starts of ``arm`` (its geometry; ``arm.push`` is
    the disk world, by default the paper's), ``moves_per_start`` moves in one random
    joint direction of norm ``arm.action_length``, ``n_goals`` fresh goals per move;
    episodes in jitted chunks of at most ``chunk_size`` (see
    :func:`lazyq_jax.data.run_episodes`).

    ``disk_range``: ``None``: the disk starts at the origin for every push and the
    state is the joint angles ``q`` (``d_s = 3``).  A number ``r``: the pushes start
    with the disk uniform in ``[-r, r]^2`` and the state is ``(q, disk_scale *
    disk_xy)`` (``d_s = 5``), which the long-horizon task needs.  ``disk_scale``:
    state units per unit of disk position (1.2 = 0.12 rad / 0.1: a disk offset of one
    finger move weighs like one joint move in the neighbourhood distance).

    Online rounds (``Config.online``): episodes start with the disk where the data's
    do (the origin, or uniform in ``disk_range``) and the fingertip behind it for the
    episode's goal (``explore_start = "behind"``) or anywhere (``"anywhere"``).
    """

    arm: ArmConfig = ArmConfig()
    n_starts: int = 5000
    moves_per_start: int = 2
    n_goals: int = 100
    chunk_size: int = 1250
    disk_range: float | None = None
    disk_scale: float = 1.2
    explore_start: str = "behind"

    def __post_init__(self) -> None:
        _check(isinstance(self.arm, ArmConfig),
               f"ArmCollectConfig.arm must be an ArmConfig, got {type(self.arm).__name__}")
        _counts(self, "n_starts", "moves_per_start", "n_goals", "chunk_size")
        _positive(self, "disk_scale")
        if self.disk_range is not None:
            _positive(self, "disk_range")
        _check(self.explore_start in ("behind", "anywhere"),
               f"ArmCollectConfig.explore_start must be 'behind' or 'anywhere', got {self.explore_start!r}")

    @property
    def disk_in_state(self) -> bool:
        return self.disk_range is not None

    @property
    def state_dim(self) -> int:
        return 5 if self.disk_in_state else 3


@dataclasses.dataclass(frozen=True)
class ArmEvalConfig:
    """The arm's protocol A (Fig. 4 in joint space) and, with the disk in the state, the
    long-horizon task (Fig. 5).

    Protocol A: ``n_directions`` goals evenly spaced from 0, ``episodes_per_direction``
    episodes of at most ``max_steps`` joint moves; the disk at the origin, the arm from
    a random collision-free start with the fingertip behind the disk and within
    ``start_range`` of it (the paper's ``[-1, 1]^2``, as the finger's; the data's start box
    is ``collect.arm.start_range``, set apart).  Outcomes as the push task's.
    Long horizon: ``long_rollouts`` rollouts of at most
    ``long_max_steps`` moves, disk and target uniform in ``[-long_range,
    long_range]^2`` (at most ``collect.disk_range``: the data must have seen the disk
    there), the fingertip within ``long_finger_box`` of the disk; success within
    ``success_radius``.  ``seed``: an offset added to each seed's evaluation seed.
    """

    seed: int = 0
    n_directions: int = 16
    episodes_per_direction: int = 20
    max_steps: int = 50
    start_range: float = 1.0
    long_rollouts: int = 100
    long_max_steps: int = 300
    long_range: float = 0.3
    long_finger_box: float = 0.6
    success_radius: float = 0.05

    def __post_init__(self) -> None:
        _counts(self, "n_directions", "episodes_per_direction", "max_steps", "long_rollouts",
                "long_max_steps")
        _counts(self, "seed", minimum=0)
        _positive(self, "start_range", "long_range", "long_finger_box", "success_radius")


def check(config: Config) -> None:
    c, e = config.collect, config.eval
    if c.disk_in_state:
        _check(e.long_range <= c.disk_range,
               f"eval.long_range={e.long_range} exceeds collect.disk_range={c.disk_range}: the "
               "data would never have seen the disk there")
    _check(e.start_range > c.arm.contact_distance + c.arm.start_margin,
           f"eval.start_range={e.start_range} must exceed the fingertip-disk contact distance "
           f"{c.arm.contact_distance} + start margin: protocol A could not start anywhere")
    _check(e.long_finger_box > c.arm.contact_distance + c.arm.start_margin,
           f"eval.long_finger_box={e.long_finger_box} must exceed the fingertip-disk contact "
           f"distance {c.arm.contact_distance} + start margin")


# Neighbourhoods measured where the pushes happen: the fingertip (relative to the disk for
# arm-long) beside the joint angles weighted 0.25 (the fingertip map of
# ``episodes.fingertip_features``), radius 0.06 in that space, and local models that fit the
# neighbours' state offsets too (Eq. 4 with ``a`` extended by ``s_j - s``).  Measured on
# ``arm``, 3 seeds (``experiments/arm_levers.py``, docs/arm.md): axis goals 73.8 % and all
# 16 47.2 % against 60.0 % and 36.5 % for the paper's joint-space radius of 0.12 rad.
# Neighbourhoods grow more than the finger's (d_s = 3 or 5): the policy may use more growths.
_NEIGHBOURS = NeighbourConfig(radius_s=0.06, max_level=8, features="fingertip",
                              feature_weight=0.25, local_model="action+state")
_SMOKE = dict(train=TrainConfig(cycles=3, epochs=2, batch_size=256, width=32, target_batch_size=4096))
_SMOKE_EVAL = dict(n_directions=4, episodes_per_direction=4, long_rollouts=4, long_max_steps=60)


def presets(disk_range: float | None, start_range: float = 1.0) -> dict[str, Config]:
    """``paper`` (the paper's scale: 5000 starts x 2 moves x 100 goals, 10 x 10 cycles),
    ``online`` (round 0 of 2500 starts, then 5 rounds of the agent's own pushes, at most
    20,000 simulated moves), ``online4x`` (round 0 of the paper's 5000 starts, then 5 rounds
    of 1200 episodes, at most 40,000 simulated moves: the arm's best measured setting,
    docs/arm.md; ~30 minutes a seed on 2 CPU cores), ``static4x`` (4x the paper's random
    moves, 20,000 starts, each move stored with 25 goals instead of 100, so the rows and the
    training's cost of 1x, and a neighbourhood holds 12 distinct actions instead of 4.6:
    arm-long's best measured setting, ~8 minutes a seed) and ``smoke`` (a tiny end-to-end
    run).

    ``disk_range``: ``None`` for ``arm``; arm-long's 0.3 is its long-horizon task's range.
    ``start_range``: the box around the disk the data's fingertip starts in (the arm's
    ``start_range``): the paper finger's 1.0 for ``arm`` (protocol A starts there too);
    0.6 for ``arm-long``, its long-horizon task's start box, where 2.6 times as many of
    the random moves push the disk (docs/arm.md: "Where the data starts")."""
    name = "arm" if disk_range is None else "arm-long"
    # arm-long: where the local model prefers no action a random joint move instead of none
    # (the zero move is a fixed point: 31 of the 65 long-horizon rollouts of seeds 0-2 at 4x
    # that ran out of time sat still to the end; docs/arm.md "Where lazy Q sat still").
    neighbours = _NEIGHBOURS if disk_range is None else dataclasses.replace(
        _NEIGHBOURS, max_level=10, no_model_action="random")
    collect = ArmCollectConfig(arm=ArmConfig(start_range=start_range), disk_range=disk_range)
    paper = Config(task=name, collect=collect, eval=ArmEvalConfig(), neighbours=neighbours)
    return {
        "paper": paper,
        "online": dataclasses.replace(paper, collect=dataclasses.replace(collect, n_starts=2500),
                                      online=OnlineConfig(rounds=5, episodes=600, max_steps=8)),
        "online4x": dataclasses.replace(paper, online=OnlineConfig(rounds=5, episodes=1200, max_steps=8,
                                                                   max_moves=40000)),
        "static4x": dataclasses.replace(paper, collect=dataclasses.replace(collect, n_starts=20000,
                                                                           n_goals=25)),
        "smoke": dataclasses.replace(
            paper, collect=dataclasses.replace(collect, n_starts=400, n_goals=20, chunk_size=400),
            eval=ArmEvalConfig(**_SMOKE_EVAL), **_SMOKE),
    }
