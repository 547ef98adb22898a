"""Fitted value iteration with lazy targets (§IV-E, Eq. 10-14), all inside jit/lax.scan.

``make_train(config, action_length)`` returns a :class:`Trainer` of pure functions:

* ``init(key, data) -> TrainState`` (sized from ``data``)
* ``run_cycle(state, data, idx, n_valid=None, weights=None, projection=None) -> (state,
  metrics)``: one cycle (``weights [N, k]``: distance-weighted local fits,
  ``neighbours.fit_weights``; ``projection``: the fits' data-only part,
  :func:`lazyq_jax.targets.fit_projection`, computed once a neighbourhood set): targets from
  the parameters frozen at the start of the cycle (the DQN target network, Eq. 11-12),
  then ``epochs`` epochs of Adam on ``mean((V - Y)^2)`` (Eq. 10) in ``lax.scan``.
  With ``double_dqn`` the targets are Eq. (13)-(14) and are refreshed every epoch:
  the action comes from the fit to the *online* network's values, its value from
  the frozen network's fit.
* ``train(key, data, idx, n_valid=None, weights=None) -> (state, metrics)``: all cycles in one
  ``lax.scan``.  It keeps ``idx`` fixed; ``resample_neighbours`` is honoured by the
  runner, which draws fresh neighbourhoods between cycles.

All three are pure: ``jax.vmap`` them over keys (and datasets) to train many seeds in
one program, as the runner does.  Datasets of different sizes are stacked
by padding them to a common length (:func:`lazyq_jax.types.pad_transitions`) and
passing each one's true size ``n_valid``: rows at or beyond ``n_valid`` are never
trained on nor counted in the metrics, and a dataset trains exactly as it would
unpadded (the shuffle below draws the same order for its rows).

Sizes come from the data: ``init(key, data)`` builds the network for ``data``'s state
size and goal kind, and a trainer or state used with data of other sizes fails with a
message naming both.  The host-side driver with checkpoints, progress and resume is
the runner (:mod:`lazyq_jax.run`), through the lazy agent (:mod:`lazyq_jax.agents.lazy`).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct
from jax.sharding import Mesh, PartitionSpec as P

from lazyq_jax.config import ConfigError, TrainConfig
from lazyq_jax.local_model import expectile_loss, safe_norm
from lazyq_jax.networks import ValueNetwork, goal_kind, value_to_distance
from lazyq_jax.parallel import AXIS, check_divisible, mesh_size
from lazyq_jax.targets import (bootstrap_table, double_dqn_target, fit_projection, in_sample_target, lazy_target,
                               local_fits, multi_step_transitions)
from lazyq_jax.types import Transitions


@struct.dataclass
class TrainState:
    """Everything a cycle changes; a pytree carried by ``lax.scan`` and checkpointed."""

    params: Any
    batch_stats: Any
    opt_state: Any
    key: jax.Array  # raw uint32[2] PRNG key (checkpoint friendly)
    cycle: jax.Array  # int32: number of completed cycles


class Trainer(NamedTuple):
    config: TrainConfig
    network: ValueNetwork
    optimizer: optax.GradientTransformation
    init: Callable
    # epoch(state, data, y, key, n_valid) -> (state, mean loss): one shuffled pass towards y, the
    # regression's targets (V's; with value_head="distance" their distances, value_to_distance)
    epoch: Callable
    run_cycle: Callable
    train: Callable
    value_fn: Callable  # value_fn(state) -> V(s[B, d_s], g) in inference mode
    #: projection(data, idx, weights) -> P [N, 1 + n_a, k] or None: the fits' data-only part
    projection: Callable


def shuffle(key: jax.Array, n: int, n_valid: jax.Array) -> jax.Array:
    """A uniformly random order of the rows ``0 .. n_valid - 1``, followed by the rest.

    Rows are sorted by 32 random bits drawn per row position (``bits(key, (n,))[i]``:
    the same for row ``i`` whatever ``n`` is), ties by position, so a dataset padded
    to any length shuffles its valid rows exactly as it would unpadded.
    """
    rows = jnp.arange(n, dtype=jnp.int32)
    bits = jax.random.bits(key, (n,), jnp.uint32)
    return jax.lax.sort((rows >= n_valid, bits, rows), num_keys=2)[2]


def masked_mean(x: jax.Array, valid: jax.Array) -> jax.Array:
    """Mean of ``x`` over the rows where ``valid``."""
    w = valid.astype(x.dtype)
    return jnp.sum(x * w) / jnp.maximum(jnp.sum(w), 1)


def check_mesh(config: TrainConfig, mesh: Mesh | None) -> None:
    """:class:`ConfigError` unless the device count divides both batch sizes."""
    check_divisible("train.batch_size", config.batch_size, mesh)
    check_divisible("train.target_batch_size", config.target_batch_size, mesh)


def _describe(state_dim, goal) -> str:
    goal = {None: "no goal", "angle": "angle goals g[N]"}.get(goal, f"goals g[N, {goal}]")
    return f"states s[N, {state_dim}] with {goal}"


def make_train(config: TrainConfig, action_length: float, *, action_set: str = "ball",
               state_offsets: bool = False, goal_offsets: bool = False, state_scale=1.0, probes=None, state_dim: int | None = None,
               goal: str | int | None = "from data",
               progress: Callable[[int], None] | None = None, mesh: Mesh | None = None) -> Trainer:
    """Build the pure training functions for ``config`` (see module docstring).

    ``action_length`` is ``c`` and ``action_set`` the action set (``"ball"``: ``|a| <= c``,
    the paper's, ``max_a beta.a = c |beta|`` in Eq. 7; ``"box"``: ``|a_i| <= c``, ``c sum
    |beta_i|``), for any ``n_a``.  ``state_offsets``: the local models are fitted with each
    neighbour's state offset as a covariate (:func:`lazyq_jax.targets.local_fits`), and with
    ``goal_offsets`` its goal offset too.  The
    sizes come from the data passed to ``init``:
    states ``[N, d_s]``, goals ``g[N]`` (an angle, periodic), ``g[N, d_g]`` (a vector) or
    ``None``.  ``state_dim`` and ``goal`` (``"angle"``, an int ``d_g`` or ``None``) may fix
    them instead (then ``init(key)`` needs no data, and data of other sizes are refused
    with a message naming both).  ``state_scale``: the states are divided by it (a
    number or one per dimension) before the network.  ``probes = (s[P, d_s], g)``:
    states whose values are logged every cycle (``metrics["probe_values"]``).
    ``progress``, if given, is called on the host with the epoch number after every
    epoch (through ``jax.debug.callback``) to drive a progress bar.

    ``mesh`` (see :mod:`lazyq_jax.parallel`): data-parallel training.  An epoch runs
    in ``shard_map``: every device draws the same shuffle, takes its contiguous
    share of each minibatch, and the gradients are averaged with ``pmean``; batch
    norm is synchronised (``axis_name``: its statistics are those of the whole
    minibatch, as on one device), so parameters and batch statistics stay
    replicated and equal the single-device ones up to reduction order.  The targets
    are computed split over the devices too (sharding constraints).  Pass the
    dataset replicated (``parallel.put(data, parallel.replicated(mesh))``).
    ``batch_size`` and ``target_batch_size`` must be multiples of the device count.
    """
    scale = _check_arguments(config, mesh, action_set, state_offsets, goal_offsets, state_scale,
                             state_dim, goal)
    distance = config.value_head == "distance"
    head_init = (float(value_to_distance(config.value_init, config.gamma)[0]) if distance
                 else config.value_init)
    network = ValueNetwork(width=config.width, depth=config.depth, output_init=head_init,
                           norm=config.norm, distance_gamma=config.gamma if distance else None,
                           state_scale=float(scale) if scale.ndim == 0 else tuple(scale.tolist()))
    setup = _Setup(config=config, network=network, optimizer=optax.adam(config.learning_rate),
                   # the training forward pass of one device's share (batch norm synchronised)
                   train_network=network if mesh is None else network.clone(axis_name=AXIS),
                   mesh=mesh, action_length=action_length, action_set=action_set,
                   state_offsets=state_offsets, goal_offsets=goal_offsets, scale=scale,
                   fixed=(state_dim, goal) if state_dim is not None and goal != "from data" else None,
                   probes=probes, progress=progress)
    return Trainer(config, network, setup.optimizer, functools.partial(_init, setup),
                   functools.partial(_epoch, setup), functools.partial(_run_cycle, setup),
                   functools.partial(_train, setup), functools.partial(_value_fn, setup),
                   functools.partial(_projection, setup))


def _check_arguments(config, mesh, action_set, state_offsets, goal_offsets, state_scale,
                     state_dim, goal) -> np.ndarray:
    """make_train's arguments checked before anything is built; the state scale as an array."""
    if not isinstance(config, TrainConfig):
        raise TypeError(f"make_train needs a TrainConfig, got {type(config).__name__}")
    check_mesh(config, mesh)
    if state_dim is not None and not (isinstance(state_dim, int) and state_dim >= 1):
        raise ValueError(f"state_dim must be an integer >= 1, got {state_dim!r}")
    if not (goal in ("angle", None, "from data") or (isinstance(goal, int) and goal >= 1)):
        raise ValueError(f"goal must be 'angle', None or a vector dimension >= 1, got {goal!r}")
    if goal_offsets and not state_offsets:
        raise ValueError("goal_offsets=True needs state_offsets=True (local_model 'action+state+goal')")
    if goal_offsets and config.bootstrap_goal == "row":
        raise ConfigError("train.bootstrap_goal='row' values every neighbour at the row's goal: there are "
                          "no goal offsets to fit; use neighbours.local_model='action+state'")
    if config.target_steps > 1 and config.bootstrap_goal != "neighbour":  # checked here: --set order
        raise ConfigError(f"train.target_steps={config.target_steps} follows each neighbour's own "
                          "trajectory at its own goal, so train.bootstrap_goal must stay 'neighbour'; "
                          f"set train.target_steps=1 to use bootstrap_goal={config.bootstrap_goal!r}")
    if action_set not in ("ball", "box"):
        raise ValueError(f"action_set must be 'ball' or 'box', got {action_set!r}")
    scale = np.asarray(state_scale, np.float64)
    if scale.ndim > 1 or not np.all(scale > 0):
        raise ValueError(f"state_scale must be a number > 0 or one per state dimension, got {state_scale!r}")
    return scale


@dataclasses.dataclass(frozen=True, eq=False)
class _Setup:
    """What :func:`make_train` resolved; every step of the cycle below reads it."""

    config: TrainConfig
    network: ValueNetwork
    train_network: ValueNetwork
    optimizer: optax.GradientTransformation
    mesh: Mesh | None
    action_length: float
    action_set: str
    state_offsets: bool
    goal_offsets: bool
    scale: np.ndarray
    fixed: tuple | None  # (state_dim, goal kind) when make_train fixed them
    probes: Any
    progress: Callable[[int], None] | None


def _sizes(setup: _Setup, data: Transitions | None, who: str):
    """``(d_s, goal kind)`` of ``data`` (or the fixed ones), checked against each other and the
    state scale."""
    fixed, scale = setup.fixed, setup.scale
    if data is None:
        if fixed is None:
            raise ValueError(f"{who} needs example data to size the network (init(key, data)), "
                             "or make_train(..., state_dim=..., goal=...)")
        return fixed
    found = (int(np.shape(data.s)[-1]), goal_kind(data.g))
    if fixed is not None and found != fixed:
        raise ValueError(f"{who}: the trainer was built for {_describe(*fixed)} but the data have "
                         f"{_describe(*found)}; build it for this data (leave state_dim and goal "
                         "unset to take them from the data)")
    if scale.ndim == 1 and scale.size != found[0]:
        raise ValueError(f"{who}: state_scale has {scale.size} entries but the states have "
                         f"{found[0]} dimensions")
    return found


def _check_state(setup: _Setup, state: TrainState, data: Transitions, who: str):
    d_s, kind = _sizes(setup, data, who)
    width = d_s + (0 if kind is None else 2 if kind == "angle" else kind)
    stored = int(state.params["Dense_0"]["kernel"].shape[-2])
    if stored != width:
        raise ValueError(f"{who}: the state's network takes inputs of width {stored}, but the "
                         f"data ({_describe(d_s, kind)}) encode to width {width}: the state was "
                         "trained on data of other sizes")


def _init(setup: _Setup, key: jax.Array, data: Transitions | None = None) -> TrainState:
    d_s, kind = _sizes(setup, data, "init")
    if jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
        key = jax.random.key_data(key)
    key = jnp.asarray(key, jnp.uint32)
    key, k_init = jax.random.split(key)
    example_g = None if kind is None else jnp.zeros((1,) if kind == "angle" else (1, kind))
    variables = setup.network.init(k_init, jnp.zeros((1, d_s)), example_g, train=False)
    params = variables["params"]
    return TrainState(params=params, batch_stats=variables.get("batch_stats", {}),
                      opt_state=setup.optimizer.init(params), key=key, cycle=jnp.int32(0))


def _value_fn(setup: _Setup, state: TrainState) -> Callable:
    variables = {"params": state.params, "batch_stats": state.batch_stats}
    return lambda s, g: setup.network.apply(variables, s, g, train=False)


def _projection(setup: _Setup, data: Transitions, idx: jax.Array, weights=None):
    """The local fits' data-only part for these neighbourhoods (:func:`fit_projection`), or
    None where the cycle fits no local model or needs more than ``alpha, beta``
    (``target_max`` ``"next"``, ``"expectile"``).  The neighbourhoods, actions and offsets
    do not change between cycles, so a cycle's fits are then a gather and a product."""
    config = setup.config
    if config.target_max in ("next", "expectile"):
        return None
    return fit_projection(data, idx, state_offsets=setup.state_offsets,
                          goal_offsets=setup.goal_offsets, weights=weights,
                          batch_size=config.target_batch_size, mesh=setup.mesh)


def _local_fits(setup: _Setup, state: TrainState, paths: Transitions, gamma, idx: jax.Array, weights,
                projection=None):
    """Eq. (5)-(6): each row's local model fitted to its neighbours' brackets under ``state``'s V
    (``paths``, ``gamma``: :func:`multi_step_transitions`', the data and gamma with target_steps 1;
    ``projection``: :func:`_projection`'s, which holds the ``weights``)."""
    config = setup.config
    return local_fits(_value_fn(setup, state), paths, idx, gamma=gamma,
                      batch_size=config.target_batch_size, mesh=setup.mesh,
                      state_offsets=setup.state_offsets, goal_offsets=setup.goal_offsets,
                      weights=None if projection is not None else weights,
                      in_sample=config.target_max == "expectile",
                      row_goal=config.bootstrap_goal == "row", projection=projection)


def _targets(setup: _Setup, frozen: TrainState, data: Transitions, paths: Transitions, gamma,
             idx: jax.Array, weights, projection=None):
    """The cycle's targets from the frozen network (the DQN target network, Eq. 11-12):
    ``((Y, clip active), (alpha, beta, y_nb))``; Eq. (7)-(8) by default, the ablations by
    ``train.target_max``.  The fits are None where no local model is fitted."""
    config = setup.config
    if config.target_max == "next":  # the ablation without the lazy model: own s'
        y = bootstrap_table(_value_fn(setup, frozen), paths, gamma, config.target_batch_size,
                            setup.mesh)
        return (y, jnp.zeros(y.shape, bool)), (None, None, None)
    alpha, beta, y_nb = _local_fits(setup, frozen, paths, gamma, idx, weights, projection)
    if config.target_max == "expectile":  # y_nb: the neighbours' values moved to the row
        return in_sample_target(y_nb, config.target_expectile, weights), (alpha, beta, y_nb)
    actions = data.a[idx] if config.target_max == "data" else None
    return (lazy_target(alpha, beta, y_nb, setup.action_length, config.clip, setup.action_set,
                        actions), (alpha, beta, y_nb))


def _loss(setup: _Setup, params, batch_stats, s, g, y):
    """Eq. (10): ``mean((V - Y)^2)`` over the minibatch (or IQL's expectile loss); with
    ``value_head="distance"`` the same on the distance head and ``y = u(Y)`` (a target
    above V is a distance below the head's: the expectile's weights follow the value)."""
    distance = setup.config.value_head == "distance"
    v, updates = setup.train_network.apply({"params": params, "batch_stats": batch_stats}, s, g,
                                           train=True, distance=distance, mutable=["batch_stats"])
    if setup.config.loss_expectile == 0.5:  # Eq. (10)
        squared = (v - y) ** 2
    else:  # expectile regression (IQL's)
        above = v - y if distance else y - v  # >= 0 where the target's value is at or above V
        squared = expectile_loss(above, v - y, setup.config.loss_expectile)
    return _mean_over_mesh(setup, jnp.mean(squared)), updates.get("batch_stats", batch_stats)


def _mean_over_mesh(setup: _Setup, x):
    return x if setup.mesh is None else jax.lax.pmean(x, AXIS)


def _device_epoch(setup: _Setup, state: TrainState, data: Transitions, y: jax.Array,
                  key: jax.Array, n_valid: jax.Array):
    """One device's part of an epoch of Adam on Eq. (10) (all of it without a mesh)."""
    d = mesh_size(setup.mesh)
    n = data.r.shape[0]
    batch = min(setup.config.batch_size, n // d * d)
    if batch == 0:
        raise ValueError(f"{n} transitions cannot be split over {d} devices")
    # The shuffled remainder (< batch rows) is left out of this epoch; so are padded rows.
    n_batches, live_batches = n // batch, n_valid // batch
    share = batch // d
    first = 0 if setup.mesh is None else jax.lax.axis_index(AXIS) * share
    perm = shuffle(key, n, n_valid)  # the same on every device

    def step(carry, i):
        params, batch_stats, opt_state = carry
        rows = jax.lax.dynamic_slice_in_dim(perm, i * batch + first, share)
        g = None if data.g is None else data.g[rows]
        (loss, new_stats), grads = jax.value_and_grad(
            functools.partial(_loss, setup), has_aux=True)(
            params, batch_stats, data.s[rows], g, y[rows])
        updates, new_opt = setup.optimizer.update(_mean_over_mesh(setup, grads), opt_state, params)
        return (optax.apply_updates(params, updates), new_stats, new_opt), loss

    def minibatch(carry, i):
        # Batches past a padded dataset's end change nothing and are skipped (under
        # vmap, cond becomes a select: computed, then dropped), so a dataset padded
        # to a static capacity costs the gradient steps of its valid rows only.
        return jax.lax.cond(i < live_batches, step, lambda c, _: (c, jnp.float32(0.0)),
                            carry, i)

    (params, batch_stats, opt_state), losses = jax.lax.scan(
        minibatch, (state.params, state.batch_stats, state.opt_state), jnp.arange(n_batches))
    state = state.replace(params=params, batch_stats=batch_stats, opt_state=opt_state)
    return state, jnp.sum(losses) / jnp.maximum(live_batches, 1)


def _epoch(setup: _Setup, state: TrainState, data: Transitions, y: jax.Array, key: jax.Array,
           n_valid: jax.Array | None = None):
    """One shuffled pass over the data: ``(state, mean loss)``."""
    n_valid = valid_rows(data, n_valid)
    if setup.mesh is None:
        return _device_epoch(setup, state, data, y, key, n_valid)
    # Everything in and out is replicated; inside, each device works on its share.
    return jax.shard_map(functools.partial(_device_epoch, setup), mesh=setup.mesh, in_specs=P(),
                         out_specs=P(), check_vma=False)(state, data, y, key, n_valid)


def _run_cycle(setup: _Setup, state: TrainState, data: Transitions, idx: jax.Array,
               n_valid: jax.Array | None = None, weights: jax.Array | None = None,
               projection: jax.Array | None = None):
    """One cycle of fitted value iteration: targets from the frozen network, then
    ``epochs`` epochs of regression towards them, then the cycle's metrics.  ``projection``:
    :func:`_projection` of ``data, idx, weights`` (computed once for many cycles), else the
    local models are solved afresh."""
    config = setup.config
    _check_state(setup, state, data, "run_cycle")
    n_valid = valid_rows(data, n_valid)
    valid = jnp.arange(data.r.shape[0]) < n_valid
    key, k_epochs = jax.random.split(state.key)
    # Each row's h-step transition (h <= target_steps; the data as they are with 1), once a cycle.
    paths, gamma = multi_step_transitions(data, config.target_steps, config.gamma)
    targets, (alpha, beta, y_nb) = _targets(setup, state, data, paths, gamma, idx, weights, projection)

    def one_epoch(state, xs):
        e, k = xs
        y, active = targets
        if config.double_dqn:  # Eq. (13)-(14): the online network picks the action
            _, beta_online, _ = _local_fits(setup, state, paths, gamma, idx, weights, projection)
            y, active = double_dqn_target(alpha, beta, beta_online, y_nb, setup.action_length,
                                          config.clip, setup.action_set)
        fit, capped = y, jnp.zeros(y.shape, bool)
        if config.value_head == "distance":  # the head fits the targets' distances
            fit, capped = value_to_distance(y, config.gamma)
        state, loss = _epoch(setup, state, data, fit, k, n_valid)
        if setup.progress is not None:
            jax.debug.callback(setup.progress, e)  # ordered=True needs a single device
        y_mean = masked_mean(y, valid)
        stats = (y_mean, jnp.sqrt(masked_mean((y - y_mean) ** 2, valid)),
                 masked_mean(active.astype(jnp.float32), valid), masked_mean(capped.astype(jnp.float32), valid))
        return state, (loss, stats)

    epochs = jnp.arange(config.epochs)
    state, (losses, (y_mean, y_std, clip_frac, capped_frac)) = jax.lax.scan(
        one_epoch, state, (epochs, jax.random.split(k_epochs, config.epochs)))
    state = state.replace(key=key, cycle=state.cycle + 1)
    metrics = {  # targets: those of the last epoch (all epochs' for DQN are the same)
        "loss": losses[-1],
        "loss_first_epoch": losses[0],
        "target_mean": y_mean[-1],
        "target_std": y_std[-1],
        "clip_fraction": clip_frac[-1],
    }
    if config.value_head == "distance":  # targets beyond the distance head's cap
        metrics["distance_capped_fraction"] = capped_frac[-1]
    if beta is not None:
        metrics["beta_norm_mean"] = masked_mean(safe_norm(beta), valid)
    if setup.probes is not None:
        metrics["probe_values"] = _value_fn(setup, state)(*setup.probes)
    return state, metrics


def _train(setup: _Setup, key: jax.Array, data: Transitions, idx: jax.Array,
           n_valid: jax.Array | None = None, weights: jax.Array | None = None):
    """All ``config.cycles`` cycles in one ``lax.scan``, from :func:`_init` (the local fits'
    projection computed once before them)."""
    projection = _projection(setup, data, idx, weights)

    def cycle(state, _):
        return _run_cycle(setup, state, data, idx, n_valid, weights, projection)

    return jax.lax.scan(cycle, _init(setup, key, data), None, length=setup.config.cycles)


def valid_rows(data: Transitions, n_valid: jax.Array | None) -> jax.Array:
    """``n_valid`` as an int32 scalar, or the number of rows of ``data`` if None."""
    return jnp.asarray(data.r.shape[0] if n_valid is None else n_valid, jnp.int32)
