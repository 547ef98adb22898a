"""Shared pieces of the offline baselines: the config base, networks, sampling, the scan.

Every baseline learns from the same static :class:`~lazyq_jax.types.Transitions` as
lazy Q and is built the same way:

* a frozen config dataclass derived from :class:`BaselineConfig`, validated in
  ``__post_init__`` (:class:`~lazyq_jax.config.ConfigError` naming the field and
  the allowed range);
* ``init(key) -> state`` and ``update(state, batch, key, step) -> (state, metrics)``,
  run ``config.steps`` times inside one ``jax.lax.scan`` by :func:`fit`, on
  minibatches drawn uniformly with replacement from the rows ``< n_valid``;
* ``policy(state) -> act(key, s[B, 2], g[B]) -> actions[B, 2]`` on the action circle.

Networks see the value network's input encoding
(:func:`lazyq_jax.networks.encode`: ``(x / scale, y / scale, cos g, sin g)``);
critics also see the action divided by ``c = action_length``.  Hidden layers are
Dense, LayerNorm, ReLU (no batch norm: the critics are evaluated on actions the
batch statistics never saw, e.g. the actor's or the target policy's).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable, NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp

from lazyq_jax.config import ConfigError
from lazyq_jax.networks import encode
from lazyq_jax.types import Transitions

Act = Callable[[jax.Array, jax.Array, jax.Array], jax.Array]


class Agent(NamedTuple):
    """A baseline: ``train(key, data, n_valid=None) -> (state, metrics)`` (pure; jit and
    vmap it) and ``policy(state) -> act(key, s[B, 2], g[B]) -> actions[B, 2]``."""

    name: str
    config: Any
    action_length: float
    train: Callable
    policy: Callable[[Any], Act]


# ----------------------------------------------------------------------------- validation


def check(cond: bool, msg: str) -> None:
    if not cond:
        raise ConfigError(msg)


def _number(value: Any) -> bool:
    return (isinstance(value, (int, float)) and not isinstance(value, bool)
            and math.isfinite(value))


def check_int(obj: Any, name: str, minimum: int) -> None:
    value = getattr(obj, name)
    check(isinstance(value, int) and not isinstance(value, bool) and value >= minimum,
          f"{type(obj).__name__}.{name} must be an integer >= {minimum}, got {value!r}")


def check_range(obj: Any, name: str, lo: float, hi: float, *, lo_open: bool = False,
                hi_open: bool = False) -> None:
    """``lo <(=) value <(=) hi``; ``hi = inf`` for no upper bound."""
    value = getattr(obj, name)
    ok = _number(value) and (value > lo if lo_open else value >= lo) and (
        value < hi if hi_open else value <= hi)
    interval = f"{'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
    check(ok, f"{type(obj).__name__}.{name} must be a finite number in {interval}, got {value!r}")


def check_action_length(action_length: Any) -> float:
    check(_number(action_length) and action_length > 0,
          f"action_length must be a finite number > 0, got {action_length!r}")
    return float(action_length)


@dataclasses.dataclass(frozen=True)
class BaselineConfig:
    """Fields every baseline has.

    ``steps``: gradient steps (default 24,200 = lazy Q's 10 cycles x 10 epochs x 242
    minibatches of 4096 at paper scale); ``batch_size``: rows per step, drawn
    uniformly with replacement; ``width`` x ``depth``: Dense layers of every network
    (as the value network: 9 layers of 32); ``gamma``: discount (lazy Q's 0.9);
    ``state_scale``: the state is divided by it before the network (the push task's
    ``start_range``); ``log_every``: metrics are means over blocks of this many steps.
    """

    steps: int = 24_200
    batch_size: int = 4096
    learning_rate: float = 3e-4
    width: int = 32
    depth: int = 9
    gamma: float = 0.9
    state_scale: float = 1.0
    log_every: int = 100

    def __post_init__(self) -> None:
        for name in ("steps", "batch_size", "width", "log_every"):
            check_int(self, name, 1)
        check_int(self, "depth", 2)
        check_range(self, "learning_rate", 0.0, math.inf, lo_open=True)
        check_range(self, "gamma", 0.0, 1.0, hi_open=True)
        check_range(self, "state_scale", 0.0, math.inf, lo_open=True)


# ----------------------------------------------------------------------------- networks


class MLP(nn.Module):
    """``depth`` Dense layers of ``width`` units (the last one ``out`` units, linear),
    LayerNorm + ReLU between them."""

    width: int
    depth: int
    out: int

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        for _ in range(self.depth - 1):
            x = nn.Dense(self.width)(x)
            x = nn.LayerNorm()(x)
            x = nn.relu(x)
        return nn.Dense(self.out)(x)


def mlp(config: BaselineConfig, out: int) -> MLP:
    return MLP(width=config.width, depth=config.depth, out=out)


def observe(config: BaselineConfig, s: jax.Array, g: jax.Array) -> jax.Array:
    """The value network's input encoding ``[B, 4]``."""
    return encode(s, g, config.state_scale)


def observe_action(config: BaselineConfig, s: jax.Array, g: jax.Array, a: jax.Array,
                   action_length: float) -> jax.Array:
    """Critic input ``[B, 6]``: the encoding and the action in units of ``c``."""
    return jnp.concatenate([observe(config, s, g), jnp.asarray(a, jnp.float32) / action_length],
                           axis=-1)


def init_ensemble(net: nn.Module, key: jax.Array, x: jax.Array, n: int = 2) -> Any:
    """``n`` independently initialised parameter sets, stacked on a leading axis."""
    return jax.vmap(lambda k: net.init(k, x))(jax.random.split(key, n))


def apply_ensemble(net: nn.Module, params: Any, x: jax.Array) -> jax.Array:
    """``[n, B, out]``: every member of a stacked ensemble on the same input."""
    return jax.vmap(lambda p: net.apply(p, x))(params)


def member(params: Any, i: int) -> Any:
    return jax.tree.map(lambda p: p[i], params)


def polyak(target: Any, online: Any, tau: float) -> Any:
    """``target <- (1 - tau) target + tau online``."""
    return jax.tree.map(lambda t, o: (1.0 - tau) * t + tau * o, target, online)


def select(pred: jax.Array, new: Any, old: Any) -> Any:
    """``new`` where the scalar ``pred`` holds, else ``old`` (leaf by leaf)."""
    return jax.tree.map(lambda a, b: jnp.where(pred, a, b), new, old)


# ----------------------------------------------------------------------------- actions


def unit(u: jax.Array) -> jax.Array:
    """``u / ||u||`` along the last axis with a finite gradient; ``(1, 0)`` where ``u`` is
    zero or not finite."""
    finite = jnp.all(jnp.isfinite(u), axis=-1, keepdims=True)
    u = jnp.where(finite, u, 0.0)
    sq = jnp.sum(u * u, axis=-1, keepdims=True)
    ok = finite & (sq > 0)
    fallback = jnp.zeros_like(u).at[..., 0].set(1.0)
    return jnp.where(ok, u * jax.lax.rsqrt(jnp.where(ok, sq, 1.0)), fallback)


def on_circle(u: jax.Array, action_length: float) -> jax.Array:
    """``c u / ||u||``: a move of length ``c`` (never NaN, see :func:`unit`)."""
    return action_length * unit(u)


def angle_action(theta: jax.Array, action_length: float) -> jax.Array:
    return action_length * jnp.stack([jnp.cos(theta), jnp.sin(theta)], axis=-1)


# ----------------------------------------------------------------------------- training


def valid_rows(data: Transitions, n_valid: jax.Array | int | None) -> jax.Array:
    """``n_valid`` as an int32 scalar, or the number of rows of ``data`` if None."""
    return jnp.asarray(data.r.shape[0] if n_valid is None else n_valid, jnp.int32)


def uniform_rows(key: jax.Array, batch_size: int, n_valid: jax.Array) -> jax.Array:
    """``batch_size`` rows uniform with replacement in ``[0, n_valid)`` (``n_valid``
    may be traced; ``n_valid = 0`` is treated as 1)."""
    return jax.random.randint(key, (batch_size,), 0, jnp.maximum(n_valid, 1))


def take(data: Transitions, rows: jax.Array) -> Transitions:
    return jax.tree.map(lambda x: x[rows], data)


def mask_of(batch: Transitions) -> jax.Array:
    """``1 - done``: only terminal transitions stop the bootstrap (truncations do not)."""
    return 1.0 - batch.done.astype(jnp.float32)


def log_means(metrics: dict, config: BaselineConfig) -> dict:
    """Per-step metrics ``[steps]`` reduced to means over blocks of ``log_every`` steps
    (``[max(1, steps // log_every)]``; a remainder of fewer steps is dropped)."""
    n_log = max(1, config.steps // config.log_every)
    block = config.steps // n_log

    def reduce(x):
        return jnp.mean(x[: n_log * block].reshape(n_log, block, *x.shape[1:]), axis=1)

    return jax.tree.map(reduce, metrics)


def fit(config: BaselineConfig, init: Callable, update: Callable, key: jax.Array,
        data: Transitions, n_valid: jax.Array | int | None = None,
        draw: Callable | None = None, progress: Callable[[int], None] | None = None
        ) -> tuple[Any, dict]:
    """``config.steps`` updates in one ``lax.scan``: ``(state, metrics)``.

    Step ``i`` uses ``fold_in(run_key, i)``: a minibatch of ``config.batch_size`` rows
    from ``draw(key) -> rows`` (default: uniform over ``[0, n_valid)``) and the rest of
    that key for ``update(state, batch, key, i)``.  ``progress(i + 1)`` is called on the
    host after every ``config.log_every``-th step.
    """
    n_valid = valid_rows(data, n_valid)
    if draw is None:
        draw = lambda k: uniform_rows(k, config.batch_size, n_valid)
    k_init, k_run = jax.random.split(key)

    def body(state, i):
        k_rows, k_update = jax.random.split(jax.random.fold_in(k_run, i))
        out = update(state, take(data, draw(k_rows)), k_update, i)
        if progress is not None:
            jax.lax.cond((i + 1) % config.log_every == 0,
                         lambda: jax.debug.callback(progress, i + 1), lambda: None)
        return out

    state, metrics = jax.lax.scan(body, init(k_init), jnp.arange(config.steps, dtype=jnp.int32))
    return state, log_means(metrics, config)
