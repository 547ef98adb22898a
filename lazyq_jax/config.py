"""Frozen, validated configuration dataclasses with the paper's defaults.

Every config validates itself in ``__post_init__``: a bad value fails when the
config is built (before anything is compiled) with a message that names the
field and says what is allowed.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any


class ConfigError(ValueError):
    """A configuration value is invalid."""


def _check(cond: bool, msg: str) -> None:
    if not cond:
        raise ConfigError(msg)


def _positive(obj: Any, *names: str) -> None:
    for name in names:
        value = getattr(obj, name)
        _check(
            isinstance(value, (int, float)) and math.isfinite(value) and value > 0,
            f"{type(obj).__name__}.{name} must be a finite number > 0, got {value!r}",
        )


@dataclasses.dataclass(frozen=True)
class PushConfig:
    """The pushing scene of paper §V-A-1 and its simulation settings.

    Geometry (paper): disk radius 0.25 at the origin of a 1.5 x 1.5 table, finger
    radius 0.06, actions are finger moves of length ``action_length = 0.1``.

    Anisotropic friction is viscous damping of the disk's planar motion,
    ``damping_x`` along x and ``anisotropy * damping_x`` along y.  With the
    default ``anisotropy = 4`` a head-on 45-degree push moves the disk at about
    12 degrees (cos 0.84 to the push: counted as a wrong direction by Eq. 15),
    while pushes along x or y stay on their axis (paper Fig. 2b).
    ``anisotropy = 1`` makes friction isotropic.

    Quasistatic moves: the finger travels ``action_length`` in ``move_substeps``
    equal increments of ``timestep`` seconds, then holds still for
    ``settle_substeps``; the disk starts every push at rest.

    Reward (Eq. 15): the disk counts as moved when ``|delta| >= move_threshold``;
    the direction is correct when ``cos(delta, g) > cos_threshold``.
    """

    disk_radius: float = 0.25
    finger_radius: float = 0.06
    table_half_size: float = 0.75
    action_length: float = 0.1
    timestep: float = 0.01
    move_substeps: int = 50
    settle_substeps: int = 5
    damping_x: float = 10.0
    anisotropy: float = 4.0
    disk_mass: float = 0.1
    contact_timeconst: float = 0.02
    contact_dampratio: float = 0.3
    solver_iterations: int = 1
    ls_iterations: int = 4
    move_threshold: float = 0.01
    cos_threshold: float = 0.9

    def __post_init__(self) -> None:
        _positive(self, "disk_radius", "finger_radius", "table_half_size", "action_length",
                  "timestep", "damping_x", "anisotropy", "disk_mass", "contact_timeconst",
                  "contact_dampratio", "move_threshold")
        for name in ("move_substeps", "solver_iterations", "ls_iterations"):
            value = getattr(self, name)
            _check(isinstance(value, int) and value >= 1,
                   f"PushConfig.{name} must be an integer >= 1, got {value!r}")
        _check(isinstance(self.settle_substeps, int) and self.settle_substeps >= 0,
               f"PushConfig.settle_substeps must be an integer >= 0, got {self.settle_substeps!r}")
        _check(-1.0 < self.cos_threshold < 1.0,
               f"PushConfig.cos_threshold must lie in (-1, 1), got {self.cos_threshold!r}")
        _check(self.contact_timeconst >= 2 * self.timestep,
               "PushConfig.contact_timeconst must be >= 2 * timestep (MuJoCo clamps it "
               f"otherwise), got {self.contact_timeconst} with timestep {self.timestep}")

    @property
    def contact_distance(self) -> float:
        """Centre distance at which finger and disk touch."""
        return self.disk_radius + self.finger_radius

    @property
    def substeps(self) -> int:
        return self.move_substeps + self.settle_substeps


@dataclasses.dataclass(frozen=True)
class CollectConfig:
    """Off-policy data collection (paper §V-A-3).

    ``n_starts`` finger starts uniform in ``[-start_range, start_range]^2`` outside
    the disk; from each, ``moves_per_start`` moves in one random direction; at
    every move the reward is recorded for ``n_goals`` goals drawn uniformly from
    ``[-pi, pi)``.  Pushes run in jitted batches of at most ``chunk_size`` episodes.
    """

    push: PushConfig = PushConfig()
    n_starts: int = 5000
    moves_per_start: int = 2
    n_goals: int = 100
    start_range: float = 1.0
    chunk_size: int = 2048

    def __post_init__(self) -> None:
        for name in ("n_starts", "moves_per_start", "n_goals", "chunk_size"):
            value = getattr(self, name)
            _check(isinstance(value, int) and value >= 1,
                   f"CollectConfig.{name} must be an integer >= 1, got {value!r}")
        _positive(self, "start_range")
        _check(self.start_range > self.push.contact_distance,
               f"CollectConfig.start_range={self.start_range} must exceed the finger-disk contact "
               f"distance {self.push.contact_distance} so that starts outside the disk exist")


def to_dict(config: Any) -> dict:
    """A JSON-ready dict of a (nested) config dataclass."""
    return dataclasses.asdict(config)


def from_dict(cls: type, data: dict) -> Any:
    """Rebuild a (nested) config dataclass from :func:`to_dict` output.

    Unknown keys raise :class:`ConfigError` naming them.
    """
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ConfigError(f"unknown {cls.__name__} field(s) {unknown}; known: {sorted(fields)}")
    kwargs = {}
    for name, value in data.items():
        default = fields[name].default
        if dataclasses.is_dataclass(default) and isinstance(value, dict):
            kwargs[name] = from_dict(type(default), value)
        elif isinstance(value, list):
            kwargs[name] = tuple(value)
        else:
            kwargs[name] = value
    return cls(**kwargs)
