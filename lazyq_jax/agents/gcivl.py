"""Goal-conditioned implicit V-learning (GCIVL), as OGBench's ``gcivl`` agent.

Park, Frans, Eysenbach & Levine, "OGBench: Benchmarking Offline Goal-Conditioned RL",
ICLR 2025 (arXiv:2410.20092), agent ``impls/agents/gcivl.py`` and networks
``impls/utils/networks.py`` of github.com/seohongpark/ogbench (read at commit
1d4140997f60).  The value learning is HIQL's (Park, Ghosh, Eysenbach & Levine, "HIQL:
Offline Goal-Conditioned RL with Latent States as Actions", NeurIPS 2023), IQL's
expectile regression (Kostrikov et al., ICLR 2022) with V only, no Q; the actor is AWR.

Losses, per step on one minibatch, summed and minimised by one Adam (``lr`` 3e-4):

* value (``GCIVLAgent.value_loss``): a twin ``V_1, V_2(s, g)`` and its target copy
  ``V^t_1, V^t_2``; with ``m = 1 - done`` (:func:`~lazyq_jax.agents.common.mask_of`)::

      q     = r + gamma m min(V^t_1, V^t_2)(s', g)        # next_v_t = jnp.minimum(...)
      A     = q - (V^t_1 + V^t_2)(s, g) / 2               # adv = q - v_t
      q_i   = r + gamma m V^t_i(s', g)                    # q1, q2
      L_V   = sum_i E[ |tau - 1(A < 0)| (q_i - V_i(s, g))^2 ]

  (:func:`lazyq_jax.local_model.expectile_loss` is OGBench's ``expectile_loss(adv, diff,
  expectile)``: the weight ``tau`` where ``adv >= 0``, else ``1 - tau``, times ``diff^2``;
  the weight comes from the target network, the difference from the online one);
* actor, AWR (``GCIVLAgent.actor_loss``), with the online values not differentiated::

      A_pi  = (V_1 + V_2)(s', g) / 2 - (V_1 + V_2)(s, g) / 2    # adv = nv - v
      L_pi  = -E[ min(exp(alpha A_pi), 100) log pi(a | s, g) ]    # alpha = 10

* target (``target_update``): ``V^t <- tau V + (1 - tau) V^t`` with ``tau`` 0.005,
  where ``V`` are the online parameters *before* this step's gradient update (OGBench
  reads them from the agent being updated, ``self.network.params``), and ``V^t = V`` at
  initialisation.  Not OGBench's, for ablations towards lazy Q's fitted value iteration
  (``docs/pointmaze.md``): ``target_period = P > 0`` replaces the averaging by a hard
  copy ``V^t <- V`` before the loss of every step ``i`` with ``i % P == 0``, so steps
  ``[cP, (c + 1)P)`` regress on targets of the parameters at step ``cP``, as lazy Q's
  cycles of §V-A-4 do.

Networks (:mod:`lazyq_jax.agents.gcbc`): values ``GCValue(ensemble=True)``: OGBench's
MLP, ``depth - 1`` hidden layers of ``width`` (Dense, GELU, LayerNorm if
``layer_norm``) and a linear output; the actor is GCBC's Gaussian ``N(c u, c)`` per
component with a state-independent, constant std (``const_std=True``), no tanh squash.
Its log-likelihood, :func:`~lazyq_jax.agents.common.log_likelihood`, is in the box
OGBench's ``MultivariateNormalDiag(u, 1).log_prob(a / c)`` plus the constant
``n_a / 2 log(2 pi)``: the AWR weights do not depend on the actor, so the gradients
are OGBench's; on the sphere (``"ball"``, not in OGBench) it is ``cos(u, a)``
(von Mises-Fisher, ``kappa = 1``).  Acting: the mean projected onto the action set
(OGBench's mode, clipped to the box).

Goals, as OGBench's: on trajectory data (``Transitions.traj_last``, e.g. the point maze)
every minibatch draws fresh ``value_goals`` (current state 0.2 / geometric future 0.5 /
random 0.3, with their ``r = success - 1`` and ``done = success``) and ``actor_goals`` (a
uniform future state of the same trajectory; with ``actor_p_randomgoal = p``, OGBench's
stitch setting 0.5, a random state with ``p``) from the trajectories
(:mod:`lazyq_jax.agents.goals`, ``goals="auto"``); on other data (or ``goals="rows"``) each
row's own goal, reward and ``done`` serve every loss.  Deviations from OGBench.  Inputs are
:func:`~lazyq_jax.agents.common.observe` (states divided by ``problem.state_scale``,
angle goals as ``cos, sin``); the exp-advantage clip 100 is ``max_weight``; steps from
``BaselineConfig.steps`` (OGBench 1M); the twin ensemble is initialised by vmapping
over two keys (OGBench: ``nn.vmap`` with split rngs, the same distribution).  No
discrete actions, no visual encoders.
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
    check,
    check_int,
    check_range,
    init_ensemble,
    log_likelihood,
    mask_of,
    observe,
    polyak,
    project,
    select,
)
from lazyq_jax.agents.gcbc import actor_mean, actor_net, actor_stats, value_net
from lazyq_jax.agents.goals import (
    actor_goals,
    check_actor_goals,
    check_goal_source,
    minibatches,
    uses_trajectories,
)
from lazyq_jax.config import ConfigError
from lazyq_jax.local_model import expectile_loss
from lazyq_jax.targets import multi_step_rows
from lazyq_jax.types import Transitions


def check_bool(obj: Any, name: str) -> None:
    value = getattr(obj, name)
    check(isinstance(value, bool),
          f"{type(obj).__name__}.{name} must be True or False, got {value!r}")


def ivl_value_loss(next_v_t: jax.Array, v_t: jax.Array, v_i: jax.Array, b: Transitions,
                   gamma: float, expectile: float) -> tuple[jax.Array, dict]:
    """OGBench's IVL value loss (the module docstring's ``L_V``; HIQL's too) from the target
    twin at ``s'`` and ``s`` (``next_v_t``, ``v_t``) and the online twin at ``s`` (``v_i``),
    each ``[2, B]``, and the metrics."""
    m = mask_of(b)
    q = b.r + gamma * m * jnp.min(next_v_t, axis=0)
    adv = q - jnp.mean(v_t, axis=0)
    q_i = b.r + gamma * m * next_v_t                                     # q1, q2
    value_loss = jnp.sum(jnp.mean(expectile_loss(adv, q_i - v_i, expectile), axis=1))
    v = jnp.mean(v_i, axis=0)
    return value_loss, {"value_loss": value_loss, "v_mean": jnp.mean(v),
                        "v_max": jnp.max(v), "v_min": jnp.min(v)}


@dataclasses.dataclass(frozen=True)
class GCIVLConfig(BaselineConfig):
    """:class:`BaselineConfig` with OGBench's ``gcivl`` defaults (``batch_size`` 1024,
    ``learning_rate`` 3e-4, ``width`` 512 x ``depth`` 4 = hidden (512, 512, 512) and the
    output layer, ``gamma`` 0.99) plus ``tau`` (target rate, 0.005), ``expectile``
    (0.9, in (0, 1)), ``alpha`` (AWR temperature, 10, >= 0; 0 is plain GCBC),
    ``max_weight`` (clip of ``exp(alpha A)``, 100) and ``layer_norm`` (in the value
    networks, True).
    ``goals``: where the goals of a minibatch come from: ``"auto"`` (default) OGBench's
    fresh value and actor goals from the trajectories when the data have them
    (``Transitions.traj_last``, :mod:`lazyq_jax.agents.goals`), else the rows' own goals;
    ``"trajectories"`` (required) or ``"rows"``.  ``target_period``: 0 (OGBench's) the
    Polyak target, ``P > 0`` a hard copy every ``P`` steps (the module docstring).
    ``target_steps``: 1 (OGBench's) or ``H > 1``, not OGBench's, a control for lazy Q's
    ``train.target_steps``: the value loss's ``r + gamma m V^t(s', g)`` becomes each value
    row's return over up to ``H`` steps of its own trajectory at its fresh goal,
    bootstrapped where the path stopped (:func:`lazyq_jax.targets.multi_step_rows`); the
    actor's advantage stays one step.  Needs OGBench's goals from the trajectories.
    ``actor_p_randomgoal``: OGBench's actor goals (:func:`~lazyq_jax.agents.goals.actor_goals`):
    a random state with this probability, else a uniform later state of the row's trajectory
    (0, OGBench's default; 0.5 its stitch datasets' setting, ``impls/hyperparameters.sh``; in
    ``[0, 1]``; above 0 needs goals from the trajectories)."""

    batch_size: int = 1024
    learning_rate: float = 3e-4
    width: int = 512
    depth: int = 4
    gamma: float = 0.99
    tau: float = 0.005
    expectile: float = 0.9
    alpha: float = 10.0
    max_weight: float = 100.0
    layer_norm: bool = True
    goals: str = "auto"
    target_period: int = 0
    target_steps: int = 1
    actor_p_randomgoal: float = 0.0

    def __post_init__(self) -> None:
        super().__post_init__()
        check_range(self, "tau", 0.0, 1.0, lo_open=True)
        check_int(self, "target_period", 0)
        check_int(self, "target_steps", 1)
        check_range(self, "expectile", 0.0, 1.0, lo_open=True, hi_open=True)
        check_range(self, "alpha", 0.0, math.inf)
        check_range(self, "max_weight", 0.0, math.inf, lo_open=True)
        check_bool(self, "layer_norm")
        check_goal_source(self)
        check_actor_goals(self)


class GCIVL(Baseline):
    name = "gcivl"
    config_class = GCIVLConfig

    def __init__(self, config=None, problem=None, progress=None):
        super().__init__(config, problem, progress)
        self.value_net = value_net(self.config, self.config.layer_norm)
        self.optimizer = optax.adam(self.config.learning_rate)

    def init_model(self, key: jax.Array, spec: Spec) -> Any:
        kv, kp = jax.random.split(key)
        ex = spec.example()
        x = observe(self.problem, ex.s, ex.g)
        params = {"value": init_ensemble(self.value_net, kv, x),
                  "actor": actor_net(self.config, spec.action_dim).init(kp, x)}
        return {"params": params, "target_value": params["value"],
                "opt": self.optimizer.init(params)}

    def values(self, value: Any, s: jax.Array, g: jax.Array | None) -> jax.Array:
        """``[2, B]``: both members of the twin ``V(s, g)``."""
        return apply_ensemble(self.value_net, value, observe(self.problem, s, g))[..., 0]

    def value_loss(self, params: Any, target_value: Any, b: Transitions, discount=None):
        """``discount [B]``: each row's ``gamma^h`` with ``target_steps`` (else ``gamma``)."""
        return ivl_value_loss(self.values(target_value, b.s_next, b.g),
                              self.values(target_value, b.s, b.g),
                              self.values(params["value"], b.s, b.g),
                              b, self.config.gamma if discount is None else discount,
                              self.config.expectile)

    def batch(self, data, rows, key, n_valid):
        """``(value batch, actor batch)``: OGBench's goals from the trajectories, or the rows';
        with ``target_steps > 1`` also the value rows' discounts, their ``s_next`` and ``r``
        those of the paths."""
        cfg = self.config
        value, actor = minibatches(cfg.goals, data, rows, key, n_valid, cfg.gamma, self.name,
                                   actor=actor_goals(cfg.actor_p_randomgoal))
        if cfg.target_steps == 1:
            return value, actor
        if not uses_trajectories(cfg.goals, data, self.name):
            raise ConfigError(f"{self.name}: target_steps={cfg.target_steps} follows each row's "
                              "trajectory to its fresh goal, so it needs goals drawn from the "
                              "trajectories (trajectory data with state goals, goals != 'rows'); "
                              "set target_steps=1")
        s_next, r, discount = multi_step_rows(data, rows, value.g, value.r, value.done,
                                              cfg.target_steps, cfg.gamma)
        return value.replace(s_next=s_next, r=r), actor, discount

    def actor_loss(self, params: Any, b: Transitions):
        cfg = self.config
        value = jax.lax.stop_gradient(params["value"])  # OGBench: the stored parameters
        v = jnp.mean(self.values(value, b.s, b.g), axis=0)
        nv = jnp.mean(self.values(value, b.s_next, b.g), axis=0)
        adv = nv - v
        weight = jnp.minimum(jnp.exp(adv * cfg.alpha), cfg.max_weight)
        mean = actor_mean(cfg, self.problem, params["actor"], b.s, b.g)
        log_prob = log_likelihood(self.problem, mean, b.a)
        actor_loss = -jnp.mean(weight * log_prob)
        return actor_loss, {"actor_loss": actor_loss, "adv": jnp.mean(adv),
                            "weight_mean": jnp.mean(weight), "weight_max": jnp.max(weight),
                            "bc_log_prob": jnp.mean(log_prob),
                            **actor_stats(self.problem, mean, b.a)}

    def loss(self, params: Any, target_value: Any, b: Transitions,
             b_actor: Transitions | None = None, discount=None) -> tuple[jax.Array, dict]:
        """``L_V + L_pi`` (see the module docstring) and the metrics; ``b_actor``: the rows
        with the actor's goals (default ``b``); ``discount``: the value rows' (``target_steps``)."""
        value_loss, value_info = self.value_loss(params, target_value, b, discount)
        actor_loss, actor_info = self.actor_loss(params, b if b_actor is None else b_actor)
        return value_loss + actor_loss, {**value_info, **actor_info}

    def update(self, model, batch, key, step):
        """One Adam step; ``batch``: rows, or ``(value rows, actor rows[, discounts])``
        (:meth:`batch`)."""
        pair = (batch, batch) if isinstance(batch, Transitions) else batch
        period = self.config.target_period
        target = model["target_value"]
        if period > 0:  # a hard copy before this step's loss (lazy Q's cycles)
            target = select(step % period == 0, model["params"]["value"], target)
        grads, metrics = jax.grad(self.loss, has_aux=True)(model["params"], target, *pair)
        updates, opt = self.optimizer.update(grads, model["opt"], model["params"])
        params = optax.apply_updates(model["params"], updates)
        if period == 0:
            # OGBench's target_update: the online parameters before this step's update
            target = polyak(target, model["params"]["value"], self.config.tau)
        return {"params": params, "target_value": target, "opt": opt}, metrics

    def actions(self, model, s, g):
        return project(self.problem,
                       actor_mean(self.config, self.problem, model["params"]["actor"], s, g))

    def value_fn(self, state):
        """``V(s, g)`` of a trained (unstacked) state: the twin's mean, as the actor's
        advantage uses it (the runner draws it as it draws lazy Q's)."""
        value = state.model["params"]["value"]
        return lambda s, g: jnp.mean(self.values(value, s, g), axis=0)


def make(config: GCIVLConfig | None = None, problem: Problem | None = None,
         progress=None) -> GCIVL:
    """The GCIVL agent (``config`` None: OGBench's defaults)."""
    return GCIVL(config, problem, progress)
