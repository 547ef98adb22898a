"""Shared pieces of the offline baselines behind :class:`lazyq_jax.agents.base.Agent`.

Every baseline (``iql``, ``td3bc``, ``dqn``, ``naf``, ``bc``; one module each) learns from
static :class:`~lazyq_jax.types.Transitions` of any sizes and is built the same way:

* a frozen config dataclass derived from :class:`BaselineConfig`, validated in
  ``__post_init__`` (:class:`~lazyq_jax.config.ConfigError` naming the field and the
  allowed range);
* a subclass of :class:`Baseline` that implements three hooks: ``init_model(key,
  spec)`` (networks sized from the data's :class:`~lazyq_jax.agents.base.Spec`),
  ``update(model, batch, key, step) -> (model, metrics)`` (one gradient step) and
  ``actions(model, s, g) -> [B, n_a]``.  :meth:`Baseline.run_block` is the one block
  runner of all of them: ``ceil(steps / blocks)`` steps per block in one
  ``lax.scan``, minibatches of ``batch_size`` rows drawn uniformly with replacement
  from the rows ``< n_valid``, exactly ``steps`` steps over all blocks (the surplus
  steps of the last block are computed but not applied: a select on the global step,
  which is what ``vmap`` makes of a ``lax.cond`` anyway).

The training state is :class:`State`: the method's ``model`` (parameters, targets,
optimiser states), the raw PRNG key ``uint32[2]`` and the number of steps done;
step ``i`` draws from ``fold_in(key, i)``, so a block is a pure function of the state
and ``train`` (all blocks in one scan) equals ``init`` then ``blocks`` calls of
``run_block``.

Inputs: :func:`lazyq_jax.networks.encode` (states divided by ``problem.state_scale``,
goals as ``cos g, sin g``, a vector, or nothing); critics also see the action divided
by ``c = problem.action_length``.  Hidden layers are Dense, LayerNorm, ReLU (no batch
norm: critics are evaluated on actions the batch statistics never saw, e.g. the
actor's or the target policy's).

Action sets (``problem.action_set``): ``"ball"``: actions ``c u / |u|`` (every task
here moves by exactly ``c``); ``"box"``: ``|a_i| <= c``, actor heads ``c tanh(u)``.
:func:`squash` maps a network output onto the set, :func:`project` a nearby action
(e.g. a smoothed target action) to its nearest point of the set; neither is ever NaN.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
from flax import struct

from lazyq_jax.agents.base import Agent, Problem, Spec, check_params_fit, valid_rows
from lazyq_jax.config import ConfigError
from lazyq_jax.networks import encode
from lazyq_jax.types import Transitions

# ----------------------------------------------------------------------------- validation


def check(cond: bool, msg: str) -> None:
    if not cond:
        raise ConfigError(msg)


def _number(value: Any) -> bool:
    return (isinstance(value, (int, float)) and not isinstance(value, bool)
            and math.isfinite(value))


def is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def check_int(obj: Any, name: str, minimum: int) -> None:
    value = getattr(obj, name)
    check(is_int(value) and value >= minimum,
          f"{type(obj).__name__}.{name} must be an integer >= {minimum}, got {value!r}")


def check_range(obj: Any, name: str, lo: float, hi: float, *, lo_open: bool = False,
                hi_open: bool = False) -> None:
    """``lo <(=) value <(=) hi``; ``hi = inf`` for no upper bound."""
    value = getattr(obj, name)
    ok = _number(value) and (value > lo if lo_open else value >= lo) and (
        value < hi if hi_open else value <= hi)
    interval = f"{'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
    check(ok, f"{type(obj).__name__}.{name} must be a finite number in {interval}, got {value!r}")


def steps_per_block(steps: int, blocks: int) -> int:
    return -(-steps // blocks)


@dataclasses.dataclass(frozen=True)
class BaselineConfig:
    """Fields every baseline has.

    ``steps``: gradient steps (default 24,200 = lazy Q's 10 cycles x 10 epochs x 242
    minibatches of 4096 at paper scale); ``batch_size``: rows per step, drawn uniformly
    with replacement; ``width`` x ``depth``: Dense layers of every network (as the value
    network: 9 layers of 32); ``gamma``: discount (lazy Q's 0.9); ``blocks``: training
    is cut into this many calls of ``run_block`` of ``ceil(steps / blocks)`` steps each,
    ``steps`` in all: the last block is shorter when ``blocks`` does not divide ``steps``
    (and trailing blocks run no step when ``steps`` is small, e.g. 11 steps in 10
    blocks: 2, 2, 2, 2, 2, 1, 0, 0, 0, 0); metrics are means over a block's steps.
    The input scale is the problem's (``Problem.state_scale``).
    """

    steps: int = 24_200
    batch_size: int = 4096
    learning_rate: float = 3e-4
    width: int = 32
    depth: int = 9
    gamma: float = 0.9
    blocks: int = 10

    def __post_init__(self) -> None:
        for name in ("steps", "batch_size", "width", "blocks"):
            check_int(self, name, 1)
        check_int(self, "depth", 2)
        check_range(self, "learning_rate", 0.0, math.inf, lo_open=True)
        check_range(self, "gamma", 0.0, 1.0, hi_open=True)


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


def apply_mlp(config: BaselineConfig, params: Any, x: jax.Array) -> jax.Array:
    """:class:`MLP` ``params`` applied to ``x``, its output width read from the parameters
    (heads whose width is sized from the data, e.g. ``n_a``)."""
    out = params["params"][f"Dense_{config.depth - 1}"]["kernel"].shape[-1]
    return mlp(config, out).apply(params, x)


def observe(problem: Problem, s: jax.Array, g: jax.Array | None) -> jax.Array:
    """The input encoding ``[B, d_s + goal width]`` (:func:`lazyq_jax.networks.encode`)."""
    return encode(s, g, problem.state_scale)


def observe_action(problem: Problem, s: jax.Array, g: jax.Array | None,
                   a: jax.Array) -> jax.Array:
    """Critic input: the encoding and the action in units of ``c``."""
    return jnp.concatenate([observe(problem, s, g),
                            jnp.asarray(a, jnp.float32) / problem.action_length], axis=-1)


def scaled_states(problem: Problem, s: jax.Array) -> jax.Array:
    """States (or goals that are states) divided by ``problem.state_scale``, in float32."""
    return jnp.asarray(s, jnp.float32) / jnp.asarray(problem.state_scale, jnp.float32)


def require_state_goals(spec: Spec, who: str, why: str) -> None:
    """``ConfigError`` unless the goals are states (``g[N, d_s]``): ``who`` (the agent)
    ``why`` (what it does with them) is the start of the message."""
    if spec.goal != spec.state_dim:
        raise ConfigError(
            f"{who} {why}, so its goals must be states (g[N, {spec.state_dim}] for states "
            f"s[N, {spec.state_dim}]); these data have {spec.describe()}: use a goal-conditioned "
            "method for other goals (lazy, gcivl)")


def init_ensemble(net: nn.Module, key: jax.Array, x: jax.Array, n: int = 2) -> Any:
    """``n`` independently initialised parameter sets, stacked on a leading axis."""
    return jax.vmap(lambda k: net.init(k, x))(jax.random.split(key, n))


def apply_ensemble(net: nn.Module, params: Any, x: jax.Array) -> jax.Array:
    """``[n, B, out]``: every member of a stacked ensemble on the same input."""
    return jax.vmap(lambda p: net.apply(p, x))(params)


def polyak(target: Any, online: Any, tau: float) -> Any:
    """``target <- (1 - tau) target + tau online``."""
    return jax.tree.map(lambda t, o: (1.0 - tau) * t + tau * o, target, online)


def select(pred: jax.Array, new: Any, old: Any) -> Any:
    """``new`` where the scalar ``pred`` holds, else ``old`` (leaf by leaf)."""
    return jax.tree.map(lambda a, b: jnp.where(pred, a, b), new, old)


# ----------------------------------------------------------------------------- actions


def unit(u: jax.Array) -> jax.Array:
    """``u / |u|`` along the last axis with a finite gradient; ``(1, 0, ..., 0)`` where ``u``
    is zero or not finite."""
    finite = jnp.all(jnp.isfinite(u), axis=-1, keepdims=True)
    u = jnp.where(finite, u, 0.0)
    sq = jnp.sum(u * u, axis=-1, keepdims=True)
    ok = finite & (sq > 0)
    fallback = jnp.zeros_like(u).at[..., 0].set(1.0)
    return jnp.where(ok, u * jax.lax.rsqrt(jnp.where(ok, sq, 1.0)), fallback)


def _finite(u: jax.Array) -> jax.Array:
    return jnp.where(jnp.isfinite(u), u, 0.0)


def squash(problem: Problem, u: jax.Array) -> jax.Array:
    """A network output ``u[..., n_a]`` as an action of the set: ``c u / |u|`` (ball) or
    ``c tanh(u)`` (box; a non-finite component counts as 0)."""
    c = problem.action_length
    if problem.action_set == "ball":
        return c * unit(u)
    return c * jnp.tanh(_finite(u))


def project(problem: Problem, a: jax.Array) -> jax.Array:
    """The nearest action of the set to ``a``: ``c a / |a|`` (ball; see :func:`unit` for
    ``a = 0``) or ``clip(a, -c, c)`` (box)."""
    c = problem.action_length
    if problem.action_set == "ball":
        return c * unit(a)
    return jnp.clip(_finite(a), -c, c)


def random_actions(key: jax.Array, problem: Problem, shape: tuple[int, ...]) -> jax.Array:
    """Uniform actions of the set, ``shape = (..., n_a)``: on the sphere ``|a| = c``
    (normalised Gaussians) or in the box ``[-c, c]^n_a``."""
    c = problem.action_length
    if problem.action_set == "ball":
        return c * unit(jax.random.normal(key, shape))
    return jax.random.uniform(key, shape, minval=-c, maxval=c)


def log_likelihood(problem: Problem, action: jax.Array, a: jax.Array) -> jax.Array:
    """``log pi(a)`` up to constants of the fixed-concentration policy centred on ``action``
    (an action of the set), per row: von Mises-Fisher with ``kappa = 1`` on the sphere
    (``cos(action, a)``; ball), a Gaussian of standard deviation ``c`` per component
    (``-|action - a|^2 / (2 c^2)``; box).  For any fixed concentration the weighted
    likelihood has the same maximiser (the concentration only scales the loss, which
    Adam undoes), and acting uses the mode."""
    if problem.action_set == "ball":
        return jnp.sum(unit(action) * unit(a), axis=-1)
    d = (action - a) / problem.action_length
    return -0.5 * jnp.sum(d * d, axis=-1)


# ----------------------------------------------------------------------------- sampling


def uniform_rows(key: jax.Array, batch_size: int, n_valid: jax.Array) -> jax.Array:
    """``batch_size`` rows uniform with replacement in ``[0, n_valid)`` (``n_valid``
    may be traced; ``n_valid = 0`` is treated as 1)."""
    return jax.random.randint(key, (batch_size,), 0, jnp.maximum(n_valid, 1))


def take(data: Transitions, rows: jax.Array) -> Transitions:
    return jax.tree.map(lambda x: x[rows], data)


def mask_of(batch: Transitions) -> jax.Array:
    """``1 - done``: only terminal transitions stop the bootstrap (truncations do not)."""
    return 1.0 - batch.done.astype(jnp.float32)


def raw_key(key: jax.Array) -> jax.Array:
    """A typed key (``jax.random.key``) as its raw ``uint32[2]`` data; raw keys pass."""
    key = jnp.asarray(key) if not hasattr(key, "dtype") else key
    if jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
        return jax.random.key_data(key)
    return key


# ----------------------------------------------------------------------------- the agent


@struct.dataclass
class State:
    """A baseline's training state (arrays only; checkpointed with orbax).

    ``model``: the method's parameters, targets and optimiser states; ``key``: raw
    ``uint32[2]``, step ``i`` draws from ``fold_in(key, i)``; ``step``: steps done."""

    model: Any
    key: jax.Array
    step: jax.Array


Sampler = tuple[Callable[[jax.Array], jax.Array], jax.Array, dict]


class Baseline(Agent):
    """The shared part of every baseline: :meth:`init`, :meth:`run_block` and :meth:`act`
    on top of the hooks :meth:`init_model`, :meth:`update` and :meth:`actions`.

    ``progress``, if given, is called on the host with the number of steps done at the
    end of every block (``jax.debug.callback``; once per seed under ``vmap``)."""

    name = "baseline"
    config_class: type = BaselineConfig

    def __init__(self, config: BaselineConfig | None = None, problem: Problem | None = None,
                 progress: Callable[[int], None] | None = None) -> None:
        cls = self.config_class
        config = cls() if config is None else config
        if type(config) is not cls:
            raise TypeError(f"agent {self.name!r} needs a {cls.__name__} (or None), "
                            f"got {type(config).__name__}")
        problem = Problem() if problem is None else problem
        if not isinstance(problem, Problem):
            raise TypeError(f"agent {self.name!r} needs a Problem, got {type(problem).__name__}")
        self.config, self.problem, self.blocks = config, problem, config.blocks
        self.progress = progress
        self._shapes: dict[Spec, Any] = {}

    # --- hooks
    def init_model(self, key: jax.Array, spec: Spec) -> Any:
        raise NotImplementedError

    def update(self, model: Any, batch: Transitions, key: jax.Array, step: jax.Array
               ) -> tuple[Any, dict]:
        raise NotImplementedError

    def actions(self, model: Any, s: jax.Array, g: jax.Array | None) -> jax.Array:
        raise NotImplementedError

    def batch(self, data: Transitions, rows: jax.Array, key: jax.Array, n_valid: jax.Array) -> Any:
        """The minibatch of ``rows`` that :meth:`update` receives (default: those rows;
        goal-conditioned agents draw their goals here, from ``key``)."""
        return take(data, rows)

    def sampler(self, data: Transitions, n_valid: jax.Array) -> Sampler:
        """``(draw(key) -> rows, active, extra metrics)``: minibatch rows, whether steps
        update the model at all (a skipped step leaves it as it is) and metrics of the
        data.  Default: uniform over the rows ``< n_valid``, always active."""
        return (lambda k: uniform_rows(k, self.config.batch_size, n_valid),
                jnp.bool_(True), {})

    # --- the interface
    def init(self, key: jax.Array, data: Transitions) -> State:
        k_model, k_run = jax.random.split(raw_key(key))
        return State(model=self.init_model(k_model, Spec.of(data)), key=k_run,
                     step=jnp.int32(0))

    def check_fits(self, model: Any, data: Transitions) -> None:
        """``ValueError`` naming both sizes when ``model`` was initialised for data of
        other sizes than ``data`` (instead of a shape error deep inside flax)."""
        spec = Spec.of(data)
        if spec not in self._shapes:
            self._shapes[spec] = jax.eval_shape(lambda k: self.init_model(k, spec),
                                               jax.random.PRNGKey(0))
        want = jax.tree_util.tree_leaves_with_path(self._shapes[spec])
        got = jax.tree_util.tree_leaves_with_path(model)
        who = f"{self.name} state"
        if [p for p, _ in want] != [p for p, _ in got]:
            raise ValueError(f"{who} does not have the structure of a {self.name} state for "
                             f"{spec.describe()}")
        wrong = [(path, have, need) for (path, have), (_, need) in zip(got, want)
                 if tuple(have.shape) != tuple(need.shape)]
        for path, have, need in wrong:  # input widths first: the clearest message
            if str(getattr(path[-1], "key", "")) == "kernel" and have.ndim >= 2:
                check_params_fit({"kernel": have}, int(need.shape[-2]), who, spec)
        if wrong:
            path, have, need = wrong[0]
            raise ValueError(f"{who} was initialised for data of other sizes: "
                             f"{jax.tree_util.keystr(path)} has shape {tuple(have.shape)}, but "
                             f"{spec.describe()} need {tuple(need.shape)}; initialise it on "
                             "this data (init(key, data))")

    def run_block(self, state: State, data: Transitions, aux: Any = None,
                  n_valid: Any = None) -> tuple[State, dict]:
        """``ceil(steps / blocks)`` steps (those past ``config.steps`` skipped); metrics are
        means over the executed steps, ``steps`` their number."""
        self.check_fits(state.model, data)
        n_valid = valid_rows(data, n_valid)
        draw, active, extra = self.sampler(data, n_valid)

        def body(model, i):
            step = state.step + i
            k_rows, k_update = jax.random.split(jax.random.fold_in(state.key, step))
            batch = self.batch(data, draw(k_rows), jax.random.fold_in(k_rows, 1), n_valid)
            new, metrics = self.update(model, batch, k_update, step)
            ran = step < self.config.steps  # the surplus steps of the last block: skipped
            return select(ran & active, new, model), (metrics, ran)

        per_block = steps_per_block(self.config.steps, self.config.blocks)
        model, (metrics, ran) = jax.lax.scan(body, state.model,
                                             jnp.arange(per_block, dtype=jnp.int32))
        count = jnp.sum(ran, dtype=jnp.int32)
        means = jax.tree.map(lambda x: jnp.where(active, jnp.sum(jnp.where(ran, x, 0)), 0)
                             / jnp.maximum(count, 1), metrics)
        state = State(model=model, key=state.key, step=state.step + count)
        if self.progress is not None:
            jax.debug.callback(self.progress, state.step)
        return state, {**means, **extra, "steps": count}

    def act(self, policy: State) -> Callable:
        """``act(key, s[B, d_s], g) -> [B, n_a]``: deterministic (the key is unused)."""
        return lambda key, s, g: self.actions(policy.model, s, g)

