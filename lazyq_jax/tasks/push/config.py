"""The push task's settings: the scene (§V-A-1), its data (§V-A-3), its evaluation (§V-B)
and the presets."""

from __future__ import annotations

import dataclasses

from lazyq_jax.config import Config, OnlineConfig, TrainConfig, _check, _counts, _positive

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
      implicitly, stable for any coefficient (:func:`lazyq_jax.tasks.push.env.coulomb_friction`).
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

    Online rounds (``Config.online``): each episode starts with the disk at the
    origin and the finger uniform within ``explore_range`` of it, outside it, and
    (``explore_start = "behind"``) on the side opposite the episode's goal
    (``"anywhere"``: any side).
    """

    push: PushConfig = PushConfig()
    n_starts: int = 5000
    moves_per_start: int = 2
    n_goals: int = 100
    start_range: float = 1.0
    chunk_size: int = 1250
    explore_start: str = "behind"
    explore_range: float = 0.6

    def __post_init__(self) -> None:
        _counts(self, "n_starts", "moves_per_start", "n_goals", "chunk_size")
        _positive(self, "start_range")
        _positive(self, "explore_range")
        for name in ("start_range", "explore_range"):
            _check(getattr(self, name) > self.push.contact_distance,
                   f"CollectConfig.{name}={getattr(self, name)} must exceed the finger-disk contact "
                   f"distance {self.push.contact_distance} so that starts outside the disk exist")
        _check(self.explore_start in ("behind", "anywhere"),
               f"CollectConfig.explore_start must be 'behind' or 'anywhere', got {self.explore_start!r}")


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

    ``seed``: an offset added to each seed's evaluation seed (seed ``s`` of a run is
    evaluated with the episodes of evaluation seed ``s + eval.seed``).
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

    def __post_init__(self) -> None:
        _counts(self, "n_directions", "episodes_per_direction", "max_steps", "long_rollouts",
                "long_max_steps")
        _check(isinstance(self.seed, int) and not isinstance(self.seed, bool) and self.seed >= 0,
               f"EvalConfig.seed must be an integer >= 0, got {self.seed!r}")
        _positive(self, "start_range", "long_range", "long_finger_box", "success_radius")


# The world of the first lazyq-jax releases: MuJoCo's quadratic fluid drag, a lighter contact
# damping; results in the README under "forgiving world".
FORGIVING_PUSH = PushConfig(friction="fluid", anisotropy=200.0, damping=0.05, disk_mass=0.1,
                            contact_dampratio=0.3)

PRESETS = {
    # The paper's scale: 5000 starts x 2 moves x 100 goals, 10 cycles x 10 epochs, in the
    # paper's world (Coulomb friction per table axis: random pushes rarely earn +1 for
    # diagonal goals).
    "paper": Config(task="push", collect=CollectConfig(), eval=EvalConfig()),
    # The same scale in the world of lazyq-jax <= 0.1 (quadratic drag): diagonal goals keep
    # about half the axis goals' positives, and the agent learns to push them.
    "forgiving": Config(task="push", collect=CollectConfig(push=FORGIVING_PUSH), eval=EvalConfig()),
    # Online lazy Q in the paper's world (the online data source): round 0 a random dataset of
    # 2500 starts (about 5,000 moves), then 5 rounds of the agent's own pushes, at most
    # 20,000 simulated moves in all.
    "online": Config(task="push", collect=CollectConfig(n_starts=2500), eval=EvalConfig(),
                     online=OnlineConfig(rounds=5, episodes=600, max_steps=8)),
    # Tiny end-to-end run for tests and CI (well under 2 minutes on 2 cores).
    "smoke": Config(
        task="push",
        collect=CollectConfig(n_starts=400, n_goals=20, start_range=0.7, chunk_size=400),
        train=TrainConfig(cycles=3, epochs=2, batch_size=256, width=32, target_batch_size=4096),
        eval=EvalConfig(n_directions=4, episodes_per_direction=4, long_rollouts=4,
                        long_max_steps=60),
    ),
}




def check(config: Config) -> None:
    """Cross-section checks of a push run (:class:`ConfigError` naming the fields)."""
    contact = config.collect.push.contact_distance
    for name in ("start_range", "long_finger_box"):
        value = getattr(config.eval, name)
        _check(value > contact, f"eval.{name}={value} must exceed the finger-disk contact "
               f"distance {contact} so that finger starts outside the disk exist")
