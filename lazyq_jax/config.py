"""Frozen, validated configuration dataclasses with the paper's defaults.

Every config validates itself in ``__post_init__``: a bad value fails when the
config is built (before anything is compiled) with a message that names the
field and says what is allowed.

:class:`Config` is one run: the task it runs (``task``, a name in
:mod:`lazyq_jax.tasks`), the task's own sections ``collect`` (its data) and ``eval``
(its evaluation protocols), whose classes the task defines, and the task-free
sections of the method (``neighbours``, ``train``, ``online``) and the devices
(``parallel``).  The tasks' presets (:func:`lazyq_jax.tasks.preset`) fill it in.
"""

from __future__ import annotations

import dataclasses
import math
from operator import attrgetter
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


LOCAL_MODELS = ("action", "action+state", "action+state+goal")
FIT_WEIGHTS = ("uniform", "epanechnikov")
NO_MODEL_ACTIONS = ("zero", "random")
GREEDY_ACTIONS = ("set", "data")
BOOTSTRAP_GOALS = ("neighbour", "row")


#: The settings of the lazy policy's step alone (acting, not training): ``evaluate --set``
#: and :func:`lazyq_jax.load_run` may change them for a trained run.
POLICY_FIELDS = ("neighbours.max_level", "neighbours.no_model_action", "neighbours.subgoal_steps",
                 "neighbours.greedy", "neighbours.far_subgoal_steps")


def policy_settings(config: "Config") -> dict:
    """``config``'s :data:`POLICY_FIELDS`, by their dotted names."""
    return {f: attrgetter(f)(config) for f in POLICY_FIELDS}


@dataclasses.dataclass(frozen=True)
class NeighbourConfig:
    """Neighbourhoods B(s, g) of §V-A-2: ``|s - s0| < radius_s`` and ``|g - g0| < radius_g``
    (wrapped for angle goals), both radii grown by ``growth`` until ``k`` points are inside.
    ``max_level``: the most growths a policy step may use (its query has static
    capacities for that many; a query needing more gets no action, and is counted).
    ``features``: where the state distance is measured: ``"state"`` (the state itself, the
    paper's) or a feature map the task offers (e.g. the arm's ``"fingertip"``); §V-A-2
    defines B(s, g) by a distance in state space, and nothing in Eq. 4-9 requires it to
    be the network's input.  ``radius_s`` is in the units of that space.
    ``feature_weight``: a parameter of the task's feature map (the arm's ``"fingertip"``:
    the weight of the joint angles beside the fingertip).  ``local_model``: ``"action"``
    (Eq. 4-6: ``alpha + beta . a`` over each neighbourhood) or ``"action+state"`` (also
    each neighbour's state offset from the centre as a covariate: ``alpha + beta . a +
    gamma . (s_j - s)``) or ``"action+state+goal"`` (and the goal offset ``g_j - g``,
    wrapped for angles: where the value changes across the goal ball, e.g. vector goals in
    a maze).  ``fit_weights``: how the neighbours count in the local fit (Eq. 5-6):
    ``"uniform"`` (the paper's least squares) or ``"epanechnikov"`` (weighted least squares
    with ``(1 - d_s^2 / R_s^2)(1 - d_g^2 / R_g^2)``, ``d`` a neighbour's distance from the
    centre in the search space and ``R`` the radii of its neighbourhood's level: the
    nearest neighbours count most, so the fit is more local than the ball).  The tasks set
    the radii of their own spaces (e.g. radians in joint space).
    ``no_model_action``: what a policy step does where the local model prefers no action
    (no neighbourhood within ``max_level`` growths, or every neighbour took the same
    action, so Eq. 6's ``beta = 0`` and Eq. 9's argmax is the whole action set):
    ``"zero"`` (the centre of the action set, the paper's tie) or ``"random"`` (an action
    of the set's boundary drawn from the step's key: a uniform direction of the ball, a
    uniform corner of the box).  Under deterministic dynamics the zero action is a fixed
    point: the next step asks the same query, and the episode stays there.
    ``subgoal_steps``: ``0`` (the paper's policy: Eq. 9's greedy step towards the goal) or
    ``H > 0``, a two-level policy for long horizons (:func:`lazyq_jax.policy.lazy_subgoals`):
    each step picks a subgoal among the states the neighbours' trajectories reached ``H``
    steps later, by the trained ``V(w, g)``, and takes Eq. (9)'s step towards it (HIQL's
    hierarchy, with the data's states as the subgoals); it needs trajectory data whose goals
    are states, changes acting only, and costs ``3k + 1`` network evaluations a step.
    ``far_subgoal_steps``: ``0`` (the two levels above) or ``F > subgoal_steps``, three
    levels: a far subgoal among the states the neighbours' trajectories reached ``F`` steps
    later, by ``V(w, g)``, then the near subgoal (``subgoal_steps`` later) by ``V(w', w)``,
    then Eq. (9)'s step towards it: the far level compares values ``F`` steps apart, the near
    level's goal stays within its reach.  Acting only; ``6k + 2`` network evaluations a step;
    unused by the one-level step (``subgoal_steps = 0``).
    ``greedy``: Eq. (9)'s argmax of the local model ``beta . a`` over the action ``"set"``
    (the paper's: a corner of the box, the ball's boundary) or over the neighbourhood's own
    actions (``"data"``: the neighbour's action the fit values most; the step stays among
    actions the data took, where the linear model was fitted, as IQL-style in-sample
    maximisation does for targets; ``beta = 0`` is still no action).  Acting only."""

    k: int = 20
    radius_s: float = 0.06
    radius_g: float = 0.1
    growth: float = 2 ** (1 / 3)
    max_level: int = 5
    features: str = "state"
    feature_weight: float = 0.25
    local_model: str = "action"
    fit_weights: str = "uniform"
    no_model_action: str = "zero"
    subgoal_steps: int = 0
    greedy: str = "set"
    far_subgoal_steps: int = 0

    def __post_init__(self) -> None:
        _check(self.greedy in GREEDY_ACTIONS,
               f"NeighbourConfig.greedy must be one of {GREEDY_ACTIONS}, got {self.greedy!r}")
        _check(self.fit_weights in FIT_WEIGHTS,
               f"NeighbourConfig.fit_weights must be one of {FIT_WEIGHTS}, got {self.fit_weights!r}")
        _check(self.no_model_action in NO_MODEL_ACTIONS,
               f"NeighbourConfig.no_model_action must be one of {NO_MODEL_ACTIONS}, "
               f"got {self.no_model_action!r}")
        _check(isinstance(self.features, str) and bool(self.features),
               f"NeighbourConfig.features must be a feature map's name, got {self.features!r}")
        _check(isinstance(self.feature_weight, (int, float)) and not isinstance(self.feature_weight, bool)
               and 0 <= self.feature_weight < float("inf"),
               f"NeighbourConfig.feature_weight must be a number >= 0, got {self.feature_weight!r}")
        _check(self.local_model in LOCAL_MODELS,
               f"NeighbourConfig.local_model must be one of {LOCAL_MODELS}, got {self.local_model!r}")
        _counts(self, "k")
        _counts(self, "max_level", "subgoal_steps", "far_subgoal_steps", minimum=0)
        _check(self.far_subgoal_steps == 0 or self.subgoal_steps == 0
               or self.far_subgoal_steps > self.subgoal_steps,
               f"NeighbourConfig.far_subgoal_steps must be 0 (two levels) or above subgoal_steps "
               f"(a far subgoal before the near one), got far_subgoal_steps={self.far_subgoal_steps} "
               f"with subgoal_steps={self.subgoal_steps}: set neighbours.far_subgoal_steps too")
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
    ``target_max``: Eq. (7)'s maximum over the action ``"set"`` (the paper's), or over the
    neighbourhood's own actions, ``"data"`` (``alpha + max_j beta . a_j``: an in-sample
    maximum that extrapolates less; ``docs/pointmaze.md``), or ``"expectile"``: the
    ``target_expectile``-expectile of the neighbours' values moved to the row's state and goal
    by the local model's offset terms (:func:`lazyq_jax.targets.in_sample_target`: in-sample,
    as IQL's and GCIVL's expectile, never above the largest of them); the policy stays Eq. (9).
    ``"next"`` is an ablation without the lazy model in the value iteration: each row's own
    one-step target ``r_i + gamma (1 - done_i) V(s'_i, g_i)``, no neighbourhood and no maximum
    (with ``loss_expectile = 0.5`` the data's own policy is evaluated; with ``0.9`` the
    expectile regression gives GCIVL's value loss, Park et al. 2024, in lazy Q's network and
    cycles); the neighbourhoods then serve the policy (Eq. 9) only.
    ``norm``: ``"batch"`` (the paper's §V-A-4 network: Dense, BatchNorm, ReLU) or ``"layer"``
    (an ablation: OGBench's MLP blocks, Dense, GELU, LayerNorm; ``docs/pointmaze.md``).
    ``loss_expectile``: 0.5 (default) is Eq. (10)'s squared error; ``tau != 0.5`` weights each
    row's squared error by ``tau`` where the target is at or above the value, ``1 - tau`` below
    (IQL's expectile regression, Kostrikov et al. 2022: V tends to the targets'
    ``tau``-expectile).
    ``target_steps``: 1 (the paper's one-step Eq. 6) or ``H > 1``: each neighbour's
    ``y_j`` is its row's ``h``-step return along its own trajectory, ``h <= H`` (to the
    goal or the trajectory's end sooner), bootstrapped at the state reached
    (:func:`lazyq_jax.targets.multi_step_transitions`); the fit, Eq. (7)-(8)'s maximum and
    the policy are unchanged.  It needs trajectory data with state goals and a reward that
    stays the same every step until the goal (OGBench's relabelled goal reaching), and
    ``bootstrap_goal="neighbour"``.
    ``value_init``: where V starts (the last layer's initial bias; 0, the paper's, by
    default).  ``r_min / (1 - gamma)`` is a pessimistic start: V rises from below (on the
    maze it still ends above V* at the pairs across walls: ``docs/pointmaze.md``).
    ``relabel_every``: on trajectory data with state goals (``Transitions.traj_last``), every
    that many cycles the lazy agent draws every row a fresh goal as OGBench's value goals
    (:mod:`lazyq_jax.agents.goals`) and finds the neighbourhoods anew (one search each
    time); the first ``relabel_every`` cycles train on the rows' own goals.  0 (default):
    the rows' goals throughout.
    ``bootstrap_goal``: at which goal a neighbour's next state is valued in Eq. (6)'s
    ``y_j``: ``"neighbour"`` (the paper's: ``r_j + gamma V(s'_j, g_j)``, neighbourhoods in
    (state, goal) space) or ``"row"``: neighbourhoods in state space only and
    ``y_j = r_i + gamma (1 - done_i) V(s'_j, g_i)`` at the row's own goal ``g_i``, with the
    row's reward: exact where the reward and termination depend on the state and goal alone
    (OGBench's relabelled goal reaching, ``Problem.state_goal_reward``), and then no goal
    offset has to absorb how V changes across the goal radius (``docs/pointmaze.md``).  The
    policy then values each neighbour's next state at the query's goal.
    ``value_head``: what the network's last layer outputs.  ``"value"`` (default, the paper's):
    V itself, regressed by Eq. (10).  ``"distance"``: the number of steps to the goal ``d``,
    in horizons ``u = (1 - gamma) d``, with ``V = -(1 - gamma^d) / (1 - gamma)``
    (:func:`lazyq_jax.networks.distance_to_value`); every target Y is computed as before and
    the regression fits ``u`` to ``u(Y)`` (:func:`lazyq_jax.networks.value_to_distance`).
    Exact for a reward of -1 every step until the goal (OGBench's), where a one-step target
    is ``d(Y) = 1 + d(s')``: far from the goal V saturates near ``-1 / (1 - gamma)`` and the
    value's regression error hides how far, while the distance's grows linearly.  The idea
    of learning the steps to the goal rather than a discounted value is QRL's quasimetric
    (Wang et al. 2023) and HILP's temporal distance (Park et al. 2024); here it is only a
    reparameterisation of the same V.  It needs rewards in [-1, 0].
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
    target_max: str = "set"
    target_expectile: float = 0.9  # OGBench's GCIVL/GCIQL expectile
    loss_expectile: float = 0.5  # 0.5: Eq. (10)'s squared error
    norm: str = "batch"
    value_init: float = 0.0
    relabel_every: int = 0
    bootstrap_goal: str = "neighbour"
    target_steps: int = 1
    value_head: str = "value"

    def __post_init__(self) -> None:
        _counts(self, "relabel_every", minimum=0)
        _counts(self, "target_steps")
        _check(self.bootstrap_goal in BOOTSTRAP_GOALS,
               f"TrainConfig.bootstrap_goal must be 'neighbour' (V(s'_j, g_j), the paper's) or 'row' "
               f"(V(s'_j, g_i) at the row's goal), got {self.bootstrap_goal!r}")
        _check(self.target_max in ("set", "data", "expectile", "next"),
               f"TrainConfig.target_max must be 'set' (Eq. 7 over the action set), 'data' (over "
               f"the neighbourhood's actions), 'expectile' (an in-sample expectile of the "
               f"neighbours' values) or 'next' (each row's own next state, no lazy model), "
               f"got {self.target_max!r}")
        _check(not (self.target_max == "next" and self.bootstrap_goal != "neighbour"),
               "TrainConfig: target_max='next' uses no neighbours in the targets; bootstrap_goal "
               "must stay 'neighbour'")
        _check(not (self.double_dqn and self.target_max != "set"),
               "TrainConfig: double_dqn picks the action set's maximiser (Eq. 13); use it with "
               "target_max='set'")
        _check(isinstance(self.target_expectile, (int, float)) and not isinstance(self.target_expectile, bool)
               and 0.0 < self.target_expectile < 1.0,
               f"TrainConfig.target_expectile must lie strictly between 0 and 1 (0.5: the mean, "
               f"near 1: the maximum), got {self.target_expectile!r}")
        _check(self.value_head in ("value", "distance"),
               f"TrainConfig.value_head must be 'value' (the network outputs V, the paper's) or "
               f"'distance' (it outputs the steps to the goal, V follows), got {self.value_head!r}")
        _check(self.norm in ("batch", "layer"),
               f"TrainConfig.norm must be 'batch' (the paper's BatchNorm network) or 'layer' "
               f"(OGBench's LayerNorm blocks), got {self.norm!r}")
        _check(isinstance(self.loss_expectile, (int, float)) and not isinstance(self.loss_expectile, bool)
               and 0.0 < self.loss_expectile < 1.0,
               f"TrainConfig.loss_expectile must lie strictly between 0 and 1 (0.5: Eq. 10's "
               f"squared error), got {self.loss_expectile!r}")
        _check(0.0 <= self.gamma < 1.0, f"TrainConfig.gamma must lie in [0, 1), got {self.gamma!r}")
        _counts(self, "cycles", "epochs", "batch_size", "width", "target_batch_size")
        _check(_is_int(self.depth) and self.depth >= 2,
               f"TrainConfig.depth (number of Dense layers) must be an integer >= 2, got {self.depth!r}")
        _positive(self, "learning_rate")
        _check(isinstance(self.value_init, (int, float)) and not isinstance(self.value_init, bool)
               and math.isfinite(self.value_init),
               f"TrainConfig.value_init must be a finite number, got {self.value_init!r}")


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
    """Online lazy Q-learning, beyond the paper (the ``online`` data source of
    :mod:`lazyq_jax.run`).

    ``rounds = 0`` (default) is the paper's method: one static random dataset.  With
    ``rounds > 0``, round 0 trains on the task's random dataset (``collect``) for
    ``train.cycles`` cycles; then each round rolls out the current lazy policy (Eq. 9)
    in ``episodes`` batched episodes of at most ``max_steps`` moves, from the task's
    exploration starts (e.g. behind the disk for a random goal), with exploration: a
    uniformly random direction with probability ``epsilon`` (and wherever the policy
    finds no neighbourhood), else the greedy direction turned by noise of about
    ``action_noise`` radians.  Every move is relabelled for the task's goals and
    appended; then ``cycles`` training cycles continue from the current parameters.
    Each round adds at most ``(max_moves - round 0's moves) / rounds`` simulated
    moves, so the dataset never exceeds ``max_moves`` moves.  ``eval_episodes``:
    episodes per direction of the per-round check (protocol A).
    """

    rounds: int = 0
    episodes: int = 500
    max_steps: int = 8
    epsilon: float = 0.1
    action_noise: float = 0.05
    cycles: int = 2
    max_moves: int = 20000
    eval_episodes: int = 10

    def __post_init__(self) -> None:
        _counts(self, "rounds", minimum=0)
        _counts(self, "episodes", "max_steps", "cycles", "max_moves", "eval_episodes")
        _check(isinstance(self.epsilon, (int, float)) and 0.0 <= self.epsilon <= 1.0,
               f"OnlineConfig.epsilon (probability of a random move) must lie in [0, 1], "
               f"got {self.epsilon!r}")
        _check(isinstance(self.action_noise, (int, float)) and self.action_noise >= 0,
               f"OnlineConfig.action_noise (radians) must be >= 0, got {self.action_noise!r}")


@dataclasses.dataclass(frozen=True)
class Config:
    """Everything one run needs; saved as JSON in its run directory.

    ``collect`` and ``eval`` are the task's own sections (their classes come from the
    task named by ``task``); build a whole config with :func:`lazyq_jax.tasks.preset`.
    """

    task: str = "push"
    seed: int = 0
    collect: Any = None
    eval: Any = None
    neighbours: NeighbourConfig = NeighbourConfig()
    train: TrainConfig = TrainConfig()
    online: OnlineConfig = OnlineConfig()
    parallel: ParallelConfig = ParallelConfig()

    def __post_init__(self) -> None:
        _check(isinstance(self.task, str) and bool(self.task),
               f"Config.task must be a task name, got {self.task!r}")
        _check(_is_int(self.seed) and self.seed >= 0,
               f"Config.seed must be an integer >= 0, got {self.seed!r}")
        for name in ("collect", "eval"):
            _check(dataclasses.is_dataclass(getattr(self, name)),
                   f"Config.{name} must be the task's {name} config (a dataclass), got "
                   f"{getattr(self, name)!r}; build configs with lazyq_jax.tasks.preset(task, name)")


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
    optional = "None" in str(fields[name].type)
    if current is None and "str" in str(fields[name].type) and raw.lower() not in ("none", "null"):
        return dataclasses.replace(obj, **{name: raw})  # an unset optional text field (a path)
    return dataclasses.replace(obj, **{name: _parse(raw, current, optional, dotted)})


def _parse(raw: str, current: Any, optional: bool, dotted: str) -> Any:
    """``raw`` as a value of the type of ``current``: int, float, bool, str, a tuple of
    numbers (comma-separated) or, for optional fields, ``none``."""
    if optional and raw.lower() in ("none", "null"):
        return None
    kind = type(current)
    try:
        if current is None:  # an optional field that is unset: a number
            return int(raw) if raw.lstrip("-").isdigit() else float(raw)
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
        if kind is tuple:
            ints = bool(current) and all(_is_int(x) for x in current)
            return tuple((int if ints else float)(x) for x in raw.strip("()[] ").split(","))
        return kind(raw)
    except ValueError:
        what = "a comma-separated list of numbers" if kind is tuple else f"a value of type {kind.__name__}"
        raise ConfigError(f"{dotted}={raw!r}: expected {what}"
                          + (" or none" if optional else "")) from None


def to_dict(config: Any) -> dict:
    """A JSON-ready dict of a (nested) config dataclass."""
    return dataclasses.asdict(config)


def from_dict(cls: type, data: dict, sections: dict[str, type] | None = None) -> Any:
    """Rebuild a (nested) config dataclass from :func:`to_dict` output.

    ``sections``: the classes of fields whose default does not say (the task's
    ``collect`` and ``eval`` sections of :class:`Config`).  Unknown keys raise
    :class:`ConfigError` naming them.
    """
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ConfigError(f"unknown {cls.__name__} field(s) {unknown}; known: {sorted(fields)}")
    kwargs = {}
    for name, value in data.items():
        default = fields[name].default
        section = (sections or {}).get(name) or (type(default) if dataclasses.is_dataclass(default)
                                                 else None)
        if section is not None and isinstance(value, dict):
            kwargs[name] = from_dict(section, value)
        elif isinstance(value, list):
            kwargs[name] = tuple(value)
        else:
            kwargs[name] = value
    return cls(**kwargs)
