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


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _counts(obj: Any, *names: str, minimum: int = 1) -> None:
    for name in names:
        value = getattr(obj, name)
        _check(_is_int(value) and value >= minimum,
               f"{type(obj).__name__}.{name} must be an integer >= {minimum}, got {value!r}")


def _positive(obj: Any, *names: str) -> None:
    for name in names:
        value = getattr(obj, name)
        _check(
            isinstance(value, (int, float)) and not isinstance(value, bool)
            and math.isfinite(value) and value > 0,
            f"{type(obj).__name__}.{name} must be a finite number > 0, got {value!r}",
        )


FRICTION_MODELS = ("coulomb", "fluid")


@dataclasses.dataclass(frozen=True)
class PushConfig:
    """The pushing scene of paper §V-A-1 and its simulation settings.

    Geometry (paper): disk radius 0.25 at the origin of a 1.5 x 1.5 table, finger
    radius 0.06, actions are finger moves of length ``action_length = 0.1``.

    Friction of the disk on the table (paper Fig. 2b) is anisotropic: moving the
    disk along x or y is easier than moving it diagonally, so pushes along x or y
    move the disk along that axis, a push off a diagonal is deflected toward the
    nearer axis, and a push exactly along a diagonal is an unstable equilibrium.
    Axis directions are forgiving, diagonal directions are sensitive to the contact
    point and the push direction.  Two laws (``friction``):

    * ``"coulomb"`` (default; the paper's world, preset ``paper``): Coulomb friction
      ``friction_coefficient`` per table axis (its friction set is a square, so a
      diagonal slide costs sqrt 2 times an axis slide), smoothed below speeds of
      ``friction_smoothing``, plus viscous ``damping``; integrated linearly
      implicitly, stable for any coefficient (:func:`lazyq_jax.env.push.coulomb_friction`).
      The force component across the nearer axis rarely exceeds the friction, so
      the disk slides along the axis: head-on pushes at 30 / 40 / 44 degrees move it
      at about 1 / 3 / 15 degrees.  Random pushes then rarely earn +1 for diagonal
      goals (§V-B: the paper's agent could not learn them).  ``contact_dampratio``
      is 1 (no bouncing: an impact would break the friction in both axes).
    * ``"fluid"`` (preset ``forgiving``): MuJoCo's per-axis quadratic fluid drag
      (``option density = anisotropy``) in the disk's inertial frame turned by 45
      degrees; head-on pushes at 40 / 50 degrees move the disk at about 26 / 64
      degrees, and diagonal goals keep about half the axis goals' positive rewards.
      Integrated explicitly, so ``anisotropy`` is limited to ``300 * (disk_mass /
      0.1) * (0.01 / timestep)``; ``anisotropy = 0`` leaves only the isotropic
      ``damping`` (raise it then, e.g. to 10, or the disk coasts).

    ``float64``: :func:`lazyq_jax.collect` simulates in float64 (the same speed on
    CPU; it agrees with native MuJoCo to ~1e-5, while float32 rounding is amplified
    by the deflection to ~3e-3).  :class:`PushEnv` uses the precision JAX is in.

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
    friction: str = "coulomb"
    friction_coefficient: float = 2.0
    friction_smoothing: float = 0.005
    anisotropy: float = 200.0
    damping: float = 1.0
    disk_mass: float = 0.02
    contact_timeconst: float = 0.02
    contact_dampratio: float = 1.0
    solver_iterations: int = 1
    ls_iterations: int = 4
    move_threshold: float = 0.01
    cos_threshold: float = 0.9
    float64: bool = True

    def __post_init__(self) -> None:
        _positive(self, "disk_radius", "finger_radius", "table_half_size", "action_length",
                  "timestep", "damping", "disk_mass", "contact_timeconst",
                  "contact_dampratio", "move_threshold")
        # The drag is integrated explicitly: stable while timestep * drag'(v) / mass stays
        # small; 300 at the default mass 0.1 and timestep 0.01 (measured), scaled.
        limit = 300.0 * (self.disk_mass / 0.1) * (0.01 / self.timestep)
        _check(isinstance(self.anisotropy, (int, float)) and not isinstance(self.anisotropy, bool)
               and 0 <= self.anisotropy and (self.anisotropy <= limit or self.friction != "fluid"),
               f"PushConfig.anisotropy must be a number in [0, {limit:g}] (explicit drag "
               f"integration is unstable above that for this disk_mass and timestep), "
               f"got {self.anisotropy!r}")
        _check(self.friction in FRICTION_MODELS,
               f"PushConfig.friction must be one of {FRICTION_MODELS}, got {self.friction!r}")
        _positive(self, "friction_smoothing")
        _check(isinstance(self.friction_coefficient, (int, float))
               and not isinstance(self.friction_coefficient, bool) and self.friction_coefficient >= 0,
               f"PushConfig.friction_coefficient must be a number >= 0, got {self.friction_coefficient!r}")
        _counts(self, "move_substeps", "solver_iterations", "ls_iterations")
        _counts(self, "settle_substeps", minimum=0)
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
    ``[-pi, pi)``.  Pushes run in jitted batches (chunks) of at most ``chunk_size``
    episodes, one chunk per device at a time: the dataset is bitwise the same for
    any device count, and a number of chunks that the device count divides wastes
    no work (the default 1250 makes the paper's 5000 starts 4 chunks).
    """

    push: PushConfig = PushConfig()
    n_starts: int = 5000
    moves_per_start: int = 2
    n_goals: int = 100
    start_range: float = 1.0
    chunk_size: int = 1250

    def __post_init__(self) -> None:
        _counts(self, "n_starts", "moves_per_start", "n_goals", "chunk_size")
        _positive(self, "start_range")
        _check(self.start_range > self.push.contact_distance,
               f"CollectConfig.start_range={self.start_range} must exceed the finger-disk contact "
               f"distance {self.push.contact_distance} so that starts outside the disk exist")


@dataclasses.dataclass(frozen=True)
class NeighbourConfig:
    """Neighbourhoods B(s, g) of §V-A-2: ``|s - s0| < radius_s`` and wrapped
    ``|g - g0| < radius_g``, both radii grown by ``growth`` until ``k`` points are inside."""

    k: int = 20
    radius_s: float = 0.06
    radius_g: float = 0.1
    growth: float = 2 ** (1 / 3)

    def __post_init__(self) -> None:
        _counts(self, "k")
        _positive(self, "radius_s", "radius_g")
        _check(self.growth > 1, f"NeighbourConfig.growth must be > 1, got {self.growth!r}")


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Fitted value iteration of §IV-E / §V-A-4.

    ``cycles`` times: recompute the targets Y (Eq. 11, or Eq. 13 with ``double_dqn``)
    from the parameters frozen at the start of the cycle (the DQN target network),
    then ``epochs`` passes of Adam over the whole dataset on ``(V - Y)^2`` (Eq. 10).
    ``clip=False`` uses the unclipped Eq. (7) targets (the paper's ablation).
    ``resample_neighbours`` draws new k-subsets of each neighbourhood every cycle.
    """

    gamma: float = 0.9
    cycles: int = 10
    epochs: int = 10
    batch_size: int = 4096
    learning_rate: float = 1e-3
    width: int = 32  # chosen by experiments/width_study.py (README, "Training")
    depth: int = 9
    double_dqn: bool = False
    clip: bool = True
    resample_neighbours: bool = False
    target_batch_size: int = 65536

    def __post_init__(self) -> None:
        _check(0.0 <= self.gamma < 1.0, f"TrainConfig.gamma must lie in [0, 1), got {self.gamma!r}")
        _counts(self, "cycles", "epochs", "batch_size", "width", "target_batch_size")
        _check(_is_int(self.depth) and self.depth >= 2,
               f"TrainConfig.depth (number of Dense layers) must be an integer >= 2, got {self.depth!r}")
        _positive(self, "learning_rate")


@dataclasses.dataclass(frozen=True)
class EvalConfig:
    """The paper's two evaluation protocols (§V-B).

    Protocol A (Fig. 4): ``n_directions`` goal directions evenly spaced, starting at 0;
    ``episodes_per_direction`` episodes each of at most ``max_steps`` steps; the disk at the
    origin, the finger uniform in ``[-start_range, start_range]^2`` outside the disk on the
    side opposite to the goal direction.  Outcome: correct if the push that moved the disk
    has ``cos >= 0.9`` to the goal, wrong if it moved otherwise, not pushed after ``max_steps``.

    Protocol B (Fig. 5): ``long_rollouts`` rollouts of at most ``long_max_steps`` steps; disk
    and target uniform in ``[-long_range, long_range]^2``, the finger uniform outside the disk
    in a box of half-width ``long_finger_box`` around it; a high-level controller picks the
    axis goal best aligned with ``target - disk`` at every step; success when the disk is
    within ``success_radius`` of the target; failure when it leaves the table.

    ``seed`` seeds the evaluation only; ``max_level`` bounds the neighbourhood growth per
    policy step (queries beyond it get no action, and are counted).
    """

    seed: int = 0
    n_directions: int = 16
    episodes_per_direction: int = 20
    max_steps: int = 50
    start_range: float = 1.0
    long_rollouts: int = 100
    long_max_steps: int = 300
    long_range: float = 0.6
    long_finger_box: float = 0.6
    success_radius: float = 0.05
    max_level: int = 5

    def __post_init__(self) -> None:
        _counts(self, "n_directions", "episodes_per_direction", "max_steps", "long_rollouts",
                "long_max_steps")
        _check(_is_int(self.seed) and self.seed >= 0,
               f"EvalConfig.seed must be an integer >= 0, got {self.seed!r}")
        _counts(self, "max_level", minimum=0)
        _positive(self, "start_range", "long_range", "long_finger_box", "success_radius")


@dataclasses.dataclass(frozen=True)
class ParallelConfig:
    """Which devices a run uses (see :mod:`lazyq_jax.parallel`).

    ``devices``: how many devices the mesh spans; ``0`` (default) means all devices
    (of all processes when distributed).  Results do not depend on it: the dataset
    and the neighbourhoods are bitwise the same for every device count, trained
    parameters the same up to floating-point reduction order.  On CPU, more host
    devices come from ``XLA_FLAGS=--xla_force_host_platform_device_count=N``, set
    before JAX starts (the CLI does it from ``LAZYQ_HOST_DEVICES``).

    ``distributed``: call ``jax.distributed.initialize()`` first (multi-host; the
    environment variable ``LAZYQ_DISTRIBUTED=1`` does the same).  Coordinator,
    process count and id come from the cluster (SLURM, Open MPI, TPU pods, ...) or
    from ``JAX_COORDINATOR_ADDRESS``, ``JAX_NUM_PROCESSES`` and ``JAX_PROCESS_ID``.
    """

    devices: int = 0
    distributed: bool = False

    def __post_init__(self) -> None:
        _counts(self, "devices", minimum=0)
        _check(isinstance(self.distributed, bool),
               f"ParallelConfig.distributed must be true or false, got {self.distributed!r}")


@dataclasses.dataclass(frozen=True)
class OnlineConfig:
    """Online lazy Q-learning, beyond the paper (see :mod:`lazyq_jax.online`).

    ``rounds = 0`` (default) is the paper's method: one static random dataset.  With
    ``rounds > 0``, round 0 trains on the random dataset of ``collect`` for
    ``train.cycles`` cycles; then each round rolls out the current lazy policy (Eq. 9)
    in ``episodes`` batched episodes of at most ``max_steps`` moves, for goals uniform
    in ``[-pi, pi)``, the disk at the origin and the finger uniform within
    ``start_range`` of it, outside it, and (``start = "behind"``) on the side opposite
    the goal (``"anywhere"``: any side).  Exploration per move: a uniformly random
    direction with probability ``epsilon`` (and wherever the policy finds no
    neighbourhood), else the greedy direction turned by Gaussian noise of
    ``angle_noise`` radians.  Every move is relabelled for ``collect.n_goals`` goals
    (Eq. 15, §V-A-3) and appended; then ``cycles`` training cycles continue from the
    current parameters.  Each round adds at most ``(max_moves - round 0's moves) /
    rounds`` simulated moves, so the dataset never exceeds ``max_moves`` moves.
    ``eval_episodes``: episodes per direction of the per-round protocol A.
    """

    rounds: int = 0
    episodes: int = 500
    max_steps: int = 8
    start: str = "behind"
    start_range: float = 0.6
    epsilon: float = 0.1
    angle_noise: float = 0.05
    cycles: int = 2
    max_moves: int = 20000
    eval_episodes: int = 10

    def __post_init__(self) -> None:
        _counts(self, "rounds", minimum=0)
        _counts(self, "episodes", "max_steps", "cycles", "max_moves", "eval_episodes")
        _check(self.start in ("behind", "anywhere"),
               f"OnlineConfig.start must be 'behind' or 'anywhere', got {self.start!r}")
        _positive(self, "start_range")
        _check(isinstance(self.epsilon, (int, float)) and 0.0 <= self.epsilon <= 1.0,
               f"OnlineConfig.epsilon (probability of a random move) must lie in [0, 1], "
               f"got {self.epsilon!r}")
        _check(isinstance(self.angle_noise, (int, float)) and self.angle_noise >= 0,
               f"OnlineConfig.angle_noise (radians) must be >= 0, got {self.angle_noise!r}")


@dataclasses.dataclass(frozen=True)
class Config:
    """Everything one run needs; saved as JSON beside its dataset and checkpoints."""

    seed: int = 0
    collect: CollectConfig = CollectConfig()
    neighbours: NeighbourConfig = NeighbourConfig()
    train: TrainConfig = TrainConfig()
    eval: EvalConfig = EvalConfig()
    parallel: ParallelConfig = ParallelConfig()
    online: OnlineConfig = OnlineConfig()

    def __post_init__(self) -> None:
        _check(_is_int(self.seed) and self.seed >= 0,
               f"Config.seed must be an integer >= 0, got {self.seed!r}")
        o, c = self.online, self.collect
        _check(o.start_range > c.push.contact_distance,
               f"online.start_range={o.start_range} must exceed the finger-disk contact "
               f"distance {c.push.contact_distance} so that finger starts outside the disk exist")
        if o.rounds:
            round0 = c.n_starts * c.moves_per_start
            _check(o.max_moves > round0,
                   f"online.max_moves={o.max_moves} leaves no moves for the online rounds: round 0 "
                   f"may already hold collect.n_starts x moves_per_start = {round0}; raise "
                   "online.max_moves or lower collect.n_starts")
        contact = self.collect.push.contact_distance
        for name in ("start_range", "long_finger_box"):
            value = getattr(self.eval, name)
            _check(value > contact, f"eval.{name}={value} must exceed the finger-disk contact "
                   f"distance {contact} so that finger starts outside the disk exist")


# The world of the first lazyq-jax releases: MuJoCo's quadratic fluid drag, a lighter contact
# damping; results in the README under "forgiving world".
FORGIVING_PUSH = PushConfig(friction="fluid", anisotropy=200.0, damping=0.05, disk_mass=0.1,
                            contact_dampratio=0.3)

PRESETS = {
    # The paper's scale: 5000 starts x 2 moves x 100 goals, 10 cycles x 10 epochs, in the
    # paper's world (Coulomb friction per table axis: random pushes rarely earn +1 for
    # diagonal goals).
    "paper": Config(),
    # The same scale in the world of lazyq-jax <= 0.1 (quadratic drag): diagonal goals keep
    # about half the axis goals' positives, and the agent learns to push them.
    "forgiving": Config(collect=CollectConfig(push=FORGIVING_PUSH)),
    # Online lazy Q in the paper's world (lazyq_jax.online): round 0 a random dataset of
    # 2500 starts (about 5,000 moves), then 5 rounds of the agent's own pushes, at most
    # 20,000 simulated moves in all.
    "online": Config(collect=CollectConfig(n_starts=2500),
                     online=OnlineConfig(rounds=5, episodes=600, max_steps=8)),
    # Tiny end-to-end run for tests and CI (well under 2 minutes on 2 cores).
    "smoke": Config(
        collect=CollectConfig(n_starts=400, n_goals=20, start_range=0.7, chunk_size=400),
        train=TrainConfig(cycles=3, epochs=2, batch_size=256, width=32, target_batch_size=4096),
        eval=EvalConfig(n_directions=4, episodes_per_direction=4, long_rollouts=4,
                        long_max_steps=60),
    ),
}


def preset(name: str) -> Config:
    if name not in PRESETS:
        raise ConfigError(f"unknown preset {name!r}; choose one of {sorted(PRESETS)}")
    return PRESETS[name]


def override(config: Any, assignments: list[str]) -> Any:
    """Apply ``"section.field=value"`` strings, e.g. ``"train.width=128"``, ``"seed=3"``.

    Values are parsed as the field's type (int, float, bool, str); an unknown field
    or an unparsable value raises :class:`ConfigError` saying what is allowed.
    """
    for assignment in assignments:
        if "=" not in assignment:
            raise ConfigError(f"override {assignment!r} must look like section.field=value")
        dotted, raw = assignment.split("=", 1)
        config = _set(config, dotted.strip().split("."), raw.strip(), dotted)
    return config


def _set(obj: Any, path: list[str], raw: str, dotted: str) -> Any:
    fields = {f.name: f for f in dataclasses.fields(obj)}
    name = path[0]
    if name not in fields:
        where = type(obj).__name__
        raise ConfigError(f"unknown config field {dotted!r}: {where} has {sorted(fields)}")
    current = getattr(obj, name)
    if len(path) > 1:
        if not dataclasses.is_dataclass(current):
            raise ConfigError(f"{dotted!r}: {name} is a value, not a section")
        return dataclasses.replace(obj, **{name: _set(current, path[1:], raw, dotted)})
    if dataclasses.is_dataclass(current):
        raise ConfigError(f"{dotted!r} is a section; set one of its fields, e.g. {dotted}.<field>=...")
    return dataclasses.replace(obj, **{name: _parse(raw, type(current), dotted)})


def _parse(raw: str, kind: type, dotted: str) -> Any:
    try:
        if kind is bool:
            if raw.lower() in ("1", "true", "yes", "on"):
                return True
            if raw.lower() in ("0", "false", "no", "off"):
                return False
            raise ValueError(raw)
        if kind is int:
            return int(raw)
        if kind is float:
            return float(raw)
        return kind(raw)
    except ValueError:
        raise ConfigError(f"{dotted}={raw!r}: expected a value of type {kind.__name__}") from None


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
