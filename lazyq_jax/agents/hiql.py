"""Hierarchical implicit Q-learning (HIQL), as OGBench's ``hiql`` agent.

Park, Ghosh, Eysenbach & Levine, "HIQL: Offline Goal-Conditioned RL with Latent States as
Actions", NeurIPS 2023 (arXiv:2307.11949).  Implemented as OGBench's agent (Park, Frans,
Eysenbach & Levine, ICLR 2025), ``impls/agents/hiql.py``, ``HGCDataset`` in
``impls/utils/datasets.py`` and the networks of ``impls/utils/networks.py`` of
github.com/seohongpark/ogbench (read at commit 1d4140997f60), state-based, with its
defaults (``expectile`` 0.7, ``subgoal_steps`` 25, ``rep_dim`` 10, ``low_actor_rep_grad``
False, constant std), which are also its point-maze setting (``impls/hyperparameters.sh``:
``high_alpha = low_alpha = 3``).

One value and two policies.  A goal representation ``z(s, g) = sqrt(r) u / |u|``, ``u`` an
MLP of ``(s, g)`` to ``r = rep_dim`` numbers (OGBench's ``goal_rep``: length-normalised),
enters the twin value ``V_e(s, g) = h_e(s, z(s, g))``.  The high-level policy maps ``(s, g)``
to the representation of a subgoal ``subgoal_steps`` ahead, the low-level one maps ``(s,
z(s, w))`` to an action.  Acting: ``z^ = mean_high(s, g)`` length-normalised, then the
low-level mean at ``(s, z^)``, projected onto the action set (OGBench's evaluation at
temperature 0: the modes).

Losses, per step on one minibatch, summed and minimised by one Adam (``lr`` 3e-4):

* value, GCIVL's (:mod:`lazyq_jax.agents.gcivl`) with expectile 0.7 (``m = 1 - done``, ``t``
  the target heads, Polyak-averaged with ``tau`` 0.005; the goal representation is *not*
  averaged: OGBench's target value shares the online ``goal_rep``, not differentiated
  there)::

      q      = r + gamma m min_e V^t_e(s', g)        adv = q - mean_e V^t_e(s, g)
      L_V    = sum_e E[ |tau - 1(adv < 0)| (r + gamma m V^t_e(s', g) - V_e(s, g))^2 ]

* low-level actor, AWR towards the subgoal ``w`` = the state ``subgoal_steps`` later on the
  row's trajectory (or its last), ``V`` and ``z`` not differentiated::

      A_l    = V(s', w) - V(s, w)
      L_low  = -E[ min(exp(low_alpha A_l), 100) log pi_l(a | s, z(s, w)) ]

* high-level actor, AWR towards the representation of the state ``subgoal_steps`` later
  (but no later than the goal ``g``, a uniform later state of the trajectory)::

      A_h    = V(s_target, g) - V(s, g)
      L_high = -E[ min(exp(high_alpha A_h), 100) log N(z(s, s_target); mean_high(s, g), 1) ]

Goals, as OGBench's ``HGCDataset``: value goals as GCIVL's (the current state 0.2, a
geometric later state 0.5, a random state 0.3; ``r = success - 1``), the high-level goals a
uniform later state of the same trajectory (``actor_p_trajgoal = 1``), drawn every
minibatch; HIQL needs trajectory data (``Transitions.traj_last``) and goals that are states.
With ``actor_p_randomgoal = p`` (OGBench's stitch setting 0.5) a high-level goal is a random
state with ``p``, and its target then the state ``subgoal_steps`` later on the row's own
trajectory, clipped to the trajectory's last state (the random goal plays no part in it).

Networks: ``u``, ``h_e`` are OGBench's MLP (``depth - 1`` hidden layers of ``width``: Dense,
GELU, LayerNorm if ``layer_norm``; a linear output), the twin heads stacked
(:func:`~lazyq_jax.agents.common.init_ensemble`; one ``z`` for both, as OGBench's encoder
outside the ensemble); both actors are GCBC's mean networks (no LayerNorm, head at scale
1e-2) with unit std: the low-level one's Gaussian ``N(c u, c)`` in actions
(:func:`~lazyq_jax.agents.common.log_likelihood`), the high-level one's ``N(mean, 1)`` in the
representation (its log-density without the constant).  Deviations from OGBench: the pairs ``(s, g)`` of ``z`` and
the high-level actor enter as :func:`~lazyq_jax.agents.common.observe` encodes them for
every goal-conditioned agent here (the state divided by ``problem.state_scale``, the goal as
it is: the same only where the scale is 1, as on the point maze), the states beside ``z``
divided by the scale, actions in units of ``c = problem.action_length``; steps from
``BaselineConfig.steps`` (OGBench 1M); no discrete actions, no visual encoders.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import jax
import jax.numpy as jnp
import optax

from lazyq_jax.agents.base import Problem, Spec
from lazyq_jax.agents.common import (
    Baseline,
    BaselineConfig,
    apply_ensemble,
    check_int,
    check_range,
    init_ensemble,
    log_likelihood,
    observe,
    polyak,
    project,
    require_state_goals,
    scaled_states,
    take,
)
from lazyq_jax.agents.gcbc import GCMLP, actor_stats, value_net
from lazyq_jax.agents.gcivl import check_bool, ivl_value_loss
from lazyq_jax.agents.goals import (
    VALUE_GOALS,
    actor_goals,
    check_actor_goals,
    fresh_goals,
    sample_goal_rows_and_random,
    uses_trajectories,
)
from lazyq_jax.types import Transitions


@dataclasses.dataclass(frozen=True)
class HIQLConfig(BaselineConfig):
    """:class:`BaselineConfig` with OGBench's ``hiql`` defaults (``batch_size`` 1024,
    ``learning_rate`` 3e-4, ``width`` 512 x ``depth`` 4 = hidden (512, 512, 512) and the output
    layer, ``gamma`` 0.99) plus ``tau`` (target rate, 0.005), ``expectile`` (0.7),
    ``low_alpha`` and ``high_alpha`` (the AWR temperatures, 3; >= 0), ``max_weight`` (clip of
    the AWR weights, 100), ``subgoal_steps`` (25), ``rep_dim`` (the goal representation's
    size, 10) and ``layer_norm`` (in the value and the representation, True).
    ``actor_p_randomgoal``: the probability of a random high-level goal (its target the state
    ``subgoal_steps`` later, clipped to the trajectory's end), else a uniform later state of
    the trajectory (0, OGBench's default; 0.5 its stitch datasets' setting,
    ``impls/hyperparameters.sh``; in ``[0, 1]``)."""

    batch_size: int = 1024
    learning_rate: float = 3e-4
    width: int = 512
    depth: int = 4
    gamma: float = 0.99
    tau: float = 0.005
    expectile: float = 0.7
    low_alpha: float = 3.0
    high_alpha: float = 3.0
    max_weight: float = 100.0
    subgoal_steps: int = 25
    rep_dim: int = 10
    layer_norm: bool = True
    actor_p_randomgoal: float = 0.0

    def __post_init__(self) -> None:
        super().__post_init__()
        check_range(self, "tau", 0.0, 1.0, lo_open=True)
        check_range(self, "expectile", 0.0, 1.0, lo_open=True, hi_open=True)
        check_range(self, "low_alpha", 0.0, math.inf)
        check_range(self, "high_alpha", 0.0, math.inf)
        check_range(self, "max_weight", 0.0, math.inf, lo_open=True)
        check_int(self, "subgoal_steps", 1)
        check_int(self, "rep_dim", 1)
        check_bool(self, "layer_norm")
        check_actor_goals(self)


def length_normalise(u: jax.Array) -> jax.Array:
    """OGBench's ``LengthNormalize``: ``u`` scaled to length ``sqrt(dim)``."""
    return u / jnp.linalg.norm(u, axis=-1, keepdims=True) * math.sqrt(u.shape[-1])


class HIQL(Baseline):
    name = "hiql"
    config_class = HIQLConfig

    def __init__(self, config=None, problem=None, progress=None):
        super().__init__(config, problem, progress)
        cfg = self.config
        self.rep_net = GCMLP(cfg.width, cfg.depth, cfg.rep_dim, layer_norm=cfg.layer_norm)
        self.value_net = value_net(cfg, cfg.layer_norm)
        self.high_net = GCMLP(cfg.width, cfg.depth, cfg.rep_dim, layer_norm=False, out_scale=1e-2)
        self.optimizer = optax.adam(cfg.learning_rate)

    def low_net(self, action_dim: int) -> GCMLP:
        cfg = self.config
        return GCMLP(cfg.width, cfg.depth, action_dim, layer_norm=False, out_scale=1e-2)

    def check_data(self, spec: Spec) -> None:
        """Goals must be states (subgoals are states of the trajectories)."""
        require_state_goals(spec, "hiql", "takes its subgoals from the data's trajectories")

    def init_model(self, key: jax.Array, spec: Spec) -> Any:
        self.check_data(spec)
        k_rep, k_value, k_low, k_high = jax.random.split(key, 4)
        ex = spec.example()
        x = observe(self.problem, ex.s, ex.g)
        xz = jnp.concatenate([self.scaled(ex.s), jnp.zeros((1, self.config.rep_dim))], -1)
        params = {"rep": self.rep_net.init(k_rep, x),
                  "value": init_ensemble(self.value_net, k_value, xz),
                  "low": self.low_net(spec.action_dim).init(k_low, xz),
                  "high": self.high_net.init(k_high, x)}
        return {"params": params, "target_value": params["value"], "opt": self.optimizer.init(params)}

    # --- networks
    def scaled(self, s: jax.Array) -> jax.Array:
        return scaled_states(self.problem, s)

    def rep(self, rep: Any, s: jax.Array, g: jax.Array) -> jax.Array:
        """``z(s, g) [B, rep_dim]``: the length-normalised goal representation."""
        return length_normalise(self.rep_net.apply(rep, observe(self.problem, s, g)))

    def values(self, rep: Any, value: Any, s: jax.Array, g: jax.Array) -> jax.Array:
        """``[2, B]``: both heads ``h_e(s, z(s, g))`` with representation parameters ``rep``."""
        xz = jnp.concatenate([self.scaled(s), self.rep(rep, s, g)], -1)
        return apply_ensemble(self.value_net, value, xz)[..., 0]

    def low_mean(self, low: Any, s: jax.Array, z: jax.Array) -> jax.Array:
        """The low-level Gaussian's mean ``c u [B, n_a]`` at ``(s, z)`` (not projected)."""
        n_a = low["params"][f"Dense_{self.config.depth - 1}"]["kernel"].shape[-1]
        u = self.low_net(n_a).apply(low, jnp.concatenate([self.scaled(s), z], -1))
        return self.problem.action_length * u

    def high_mean(self, high: Any, s: jax.Array, g: jax.Array) -> jax.Array:
        return self.high_net.apply(high, observe(self.problem, s, g))

    # --- losses
    def value_loss(self, params: Any, target_value: Any, b: Transitions):
        rep_t = jax.lax.stop_gradient(params["rep"])  # the target shares the online goal_rep
        return ivl_value_loss(self.values(rep_t, target_value, b.s_next, b.g),
                              self.values(rep_t, target_value, b.s, b.g),
                              self.values(params["rep"], params["value"], b.s, b.g),
                              b, self.config.gamma, self.config.expectile)

    def advantage_weight(self, params: Any, s: jax.Array, s_next: jax.Array, g: jax.Array,
                         alpha: float):
        """``(min(exp(alpha A), max_weight), A)`` with ``A = V(s_next, g) - V(s, g)`` (the twin
        means, OGBench's stored parameters: not differentiated)."""
        frozen = jax.lax.stop_gradient(params)
        v = jnp.mean(self.values(frozen["rep"], frozen["value"], s, g), axis=0)
        nv = jnp.mean(self.values(frozen["rep"], frozen["value"], s_next, g), axis=0)
        adv = nv - v
        return jnp.minimum(jnp.exp(adv * alpha), self.config.max_weight), adv

    def low_actor_loss(self, params: Any, b: Transitions):
        """``b.g``: the subgoal ``w`` of each row."""
        weight, adv = self.advantage_weight(params, b.s, b.s_next, b.g, self.config.low_alpha)
        z = jax.lax.stop_gradient(self.rep(params["rep"], b.s, b.g))  # low_actor_rep_grad=False
        mean = self.low_mean(params["low"], b.s, z)
        log_prob = log_likelihood(self.problem, mean, b.a)
        loss = -jnp.mean(weight * log_prob)
        return loss, {"low_actor_loss": loss, "low_adv": jnp.mean(adv),
                      "low_weight_mean": jnp.mean(weight), "bc_log_prob": jnp.mean(log_prob),
                      **actor_stats(self.problem, mean, b.a)}

    def high_actor_loss(self, params: Any, b: Transitions):
        """``b.g``: the high-level goal, ``b.s_next``: the subgoal target of each row."""
        weight, adv = self.advantage_weight(params, b.s, b.s_next, b.g, self.config.high_alpha)
        target = self.rep(jax.lax.stop_gradient(params["rep"]), b.s, b.s_next)
        mean = self.high_mean(params["high"], b.s, b.g)
        log_prob = -0.5 * jnp.sum((mean - target) ** 2, axis=-1)  # N(mean, 1) up to a constant
        loss = -jnp.mean(weight * log_prob)
        return loss, {"high_actor_loss": loss, "high_adv": jnp.mean(adv),
                      "high_weight_mean": jnp.mean(weight), "high_log_prob": jnp.mean(log_prob),
                      "high_mse": jnp.mean((mean - target) ** 2)}

    def loss(self, params: Any, target_value: Any, b: Transitions, b_low: Transitions,
             b_high: Transitions) -> tuple[jax.Array, dict]:
        """``L_V + L_low + L_high`` (module docstring) and the metrics: ``b`` the rows with the
        value goals, ``b_low`` with the subgoals as ``g``, ``b_high`` with the high-level goals
        as ``g`` and the subgoal targets as ``s_next`` (:meth:`batch`)."""
        value_loss, value_info = self.value_loss(params, target_value, b)
        low_loss, low_info = self.low_actor_loss(params, b_low)
        high_loss, high_info = self.high_actor_loss(params, b_high)
        return value_loss + low_loss + high_loss, {**value_info, **low_info, **high_info}

    def batch(self, data, rows, key, n_valid):
        """``(value rows, low-level rows, high-level rows)`` of ``rows``, as OGBench's
        ``HGCDataset.sample`` (module docstring): the high-level goal a uniform later row of the
        trajectory, its target ``min(row + subgoal_steps, goal)``, or with
        ``actor_p_randomgoal`` a random row, its target ``min(row + subgoal_steps, last row
        of the trajectory)``."""
        uses_trajectories("trajectories", data, self.name)  # raises without trajectories
        k_value, k_high = jax.random.split(key)
        cfg = self.config
        b = take(data, rows)
        g, r, done = fresh_goals(data, rows, k_value, n_valid, cfg.gamma, VALUE_GOALS)
        final = data.traj_last[rows]
        low = b.replace(g=data.s[jnp.minimum(rows + cfg.subgoal_steps, final)])
        goal, random = sample_goal_rows_and_random(k_high, rows, data.traj_last, n_valid,
                                                   actor_goals(cfg.actor_p_randomgoal), cfg.gamma)
        target = jnp.minimum(rows + cfg.subgoal_steps, jnp.where(random, final, goal))
        high = b.replace(g=data.s[goal], s_next=data.s[target])
        return b.replace(g=g, r=r, done=done), low, high

    def update(self, model, batch, key, step):
        """One Adam step on :meth:`batch`'s three minibatches."""
        grads, metrics = jax.grad(self.loss, has_aux=True)(model["params"], model["target_value"], *batch)
        updates, opt = self.optimizer.update(grads, model["opt"], model["params"])
        params = optax.apply_updates(model["params"], updates)
        # OGBench's target_update: the online heads before this step's update
        target = polyak(model["target_value"], model["params"]["value"], self.config.tau)
        return {"params": params, "target_value": target, "opt": opt}, metrics

    def actions(self, model, s, g):
        params = model["params"]
        z = length_normalise(self.high_mean(params["high"], s, g))
        return project(self.problem, self.low_mean(params["low"], s, z))

    def value_fn(self, state):
        """``V(s, g)`` of a trained (unstacked) state: the twin's mean (the runner draws it as
        it draws lazy Q's)."""
        params = state.model["params"]
        return lambda s, g: jnp.mean(self.values(params["rep"], params["value"], s, g), axis=0)


def make(config: HIQLConfig | None = None, problem: Problem | None = None,
         progress=None) -> HIQL:
    """The HIQL agent (``config`` None: OGBench's defaults, which are its point-maze setting)."""
    return HIQL(config, problem, progress)
