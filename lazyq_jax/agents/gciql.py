"""Goal-conditioned implicit Q-learning with a DDPG+BC actor (GCIQL), as OGBench's
``gciql`` agent.

Park, Frans, Eysenbach & Levine, "OGBench: Benchmarking Offline Goal-Conditioned RL",
ICLR 2025 (arXiv:2410.20092), agent ``impls/agents/gciql.py`` (``actor_loss='ddpgbc'``)
and networks ``impls/utils/networks.py`` of github.com/seohongpark/ogbench (read at
commit 1d4140997f60).  IQL is Kostrikov, Nair & Levine, ICLR 2022 (arXiv:2110.06169);
DDPG+BC is TD3+BC's actor loss (Fujimoto & Gu, NeurIPS 2021) with OGBench's
normalisation of Q.

Losses, per step on one minibatch, summed and minimised by one Adam (``lr`` 3e-4):

* value (``GCIQLAgent.value_loss``), expectile regression of a single ``V(s, g)``
  onto the target twin critics (``m = 1 - done``)::

      Q^t   = min(Q^t_1, Q^t_2)(s, a, g)
      L_V   = E[ |tau - 1(Q^t - V < 0)| (Q^t - V(s, g))^2 ]      # expectile 0.9

* critics (``critic_loss``), with ``V(s', g)`` not differentiated::

      y     = r + gamma m V(s', g)
      L_Q   = E[ (Q_1(s, a, g) - y)^2 + (Q_2(s, a, g) - y)^2 ]

* actor, DDPG+BC (``actor_loss``, ``const_std=True``: the mode, clipped), critics not
  differentiated (gradients reach the actor through the action only)::

      a_pi  = clip(mean(s, g))                    # jnp.clip(dist.mode(), -1, 1)
      Q_pi  = min(Q_1, Q_2)(s, a_pi, g)
      L_pi  = -E[Q_pi] / sg(E|Q_pi| + 1e-6) - alpha E[ log pi(a | s, g) ]

  with ``alpha = 0.003`` (OGBench's point-maze setting, ``impls/hyperparameters.sh``
  ``--agent.alpha=0.003``; the file's own default is 0.3);
* target (``target_update``): ``Q^t <- tau Q + (1 - tau) Q^t`` with ``tau`` 0.005,
  ``Q`` the critics *before* this step's update (OGBench reads
  ``self.network.params``), ``Q^t = Q`` at initialisation.

Networks (:mod:`lazyq_jax.agents.gcbc`): ``V`` and the twin ``Q`` are OGBench's MLP
(``depth - 1`` hidden layers of ``width``: Dense, GELU, LayerNorm if ``layer_norm``;
linear output); critics see :func:`~lazyq_jax.agents.common.observe_action`, the
action divided by ``c = problem.action_length`` (OGBench's actions are already in
``[-1, 1]``).  The actor is GCBC's Gaussian ``N(c u, c)`` per component (constant std,
no tanh); ``a_pi`` is :func:`~lazyq_jax.agents.common.project` of the mean, in the box
OGBench's clip.  The log-likelihood :func:`~lazyq_jax.agents.common.log_likelihood`
is in the box OGBench's ``MultivariateNormalDiag(u, 1).log_prob(a / c)`` plus the
constant ``n_a / 2 log(2 pi)``, so ``L_pi`` differs from OGBench's by the constant
``alpha n_a / 2 log(2 pi)`` only; on the sphere (``"ball"``, not in OGBench) it is
``cos(u, a)`` (von Mises-Fisher, ``kappa = 1``) and ``a_pi = c u / |u|``.  Acting:
``a_pi`` (OGBench's evaluation uses the mode).

Goals, as OGBench's: on trajectory data (``Transitions.traj_last``, e.g. the point maze)
every minibatch draws fresh ``value_goals`` (for ``L_V`` and ``L_Q``: current state 0.2 / geometric future 0.5 /
random 0.3, with their ``r = success - 1`` and ``done = success``) and ``actor_goals`` (a
uniform future state of the same trajectory; with ``actor_p_randomgoal = p``, OGBench's
stitch setting 0.5, a random state with ``p``) from the trajectories
(:mod:`lazyq_jax.agents.goals`, ``goals="auto"``); on other data (or ``goals="rows"``) each
row's own goal, reward and ``done`` serve every loss.  Deviations from OGBench.  Inputs are :func:`~lazyq_jax.agents.common.observe` (states divided
by ``problem.state_scale``, angle goals as ``cos, sin``); steps from
``BaselineConfig.steps`` (OGBench 1M); the twin critics are initialised by vmapping
over two keys (OGBench: ``nn.vmap`` with split rngs, the same distribution).  Only the
DDPG+BC actor (OGBench's ``actor_loss='awr'`` option is not offered: GCIVL is the AWR
agent here); no discrete actions, no visual encoders.
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
    check_range,
    init_ensemble,
    log_likelihood,
    mask_of,
    observe,
    observe_action,
    polyak,
    project,
)
from lazyq_jax.agents.gcbc import actor_mean, actor_net, actor_stats, value_net
from lazyq_jax.agents.gcivl import check_bool
from lazyq_jax.agents.goals import actor_goals, check_actor_goals, check_goal_source, minibatches
from lazyq_jax.local_model import expectile_loss
from lazyq_jax.types import Transitions


def ddpg_bc_loss(problem: Problem, alpha: float, mean: jax.Array, q: jax.Array, a: jax.Array
                 ) -> tuple[jax.Array, dict]:
    """OGBench's DDPG+BC actor loss (the module docstring's ``L_pi``; QRL's and CRL's too) from
    the actor's mean ``[B, n_a]``, the critic's value ``q [B]`` of its projected mean (the
    gradient reaches the actor through the action only) and the data's actions ``a``, and the
    metrics."""
    q_loss = -jnp.mean(q) / jax.lax.stop_gradient(jnp.mean(jnp.abs(q)) + 1e-6)
    log_prob = log_likelihood(problem, mean, a)
    bc_loss = -jnp.mean(alpha * log_prob)
    actor_loss = q_loss + bc_loss
    return actor_loss, {"actor_loss": actor_loss, "q_loss": q_loss, "bc_loss": bc_loss,
                        "q_pi_mean": jnp.mean(q), "q_pi_abs_mean": jnp.mean(jnp.abs(q)),
                        "bc_log_prob": jnp.mean(log_prob), **actor_stats(problem, mean, a)}


@dataclasses.dataclass(frozen=True)
class GCIQLConfig(BaselineConfig):
    """:class:`BaselineConfig` with OGBench's ``gciql`` defaults (``batch_size`` 1024,
    ``learning_rate`` 3e-4, ``width`` 512 x ``depth`` 4 = hidden (512, 512, 512) and the
    output layer, ``gamma`` 0.99) plus ``tau`` (target rate, 0.005), ``expectile``
    (0.9, in (0, 1)), ``alpha`` (the BC coefficient of DDPG+BC, >= 0: OGBench's
    point-maze 0.003) and ``layer_norm`` (in ``V`` and ``Q``, True).
    ``goals``: where the goals of a minibatch come from: ``"auto"`` (default) OGBench's
    fresh value and actor goals from the trajectories when the data have them
    (``Transitions.traj_last``, :mod:`lazyq_jax.agents.goals`), else the rows' own goals;
    ``"trajectories"`` (required) or ``"rows"``.
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
    alpha: float = 0.003
    layer_norm: bool = True
    goals: str = "auto"
    actor_p_randomgoal: float = 0.0

    def __post_init__(self) -> None:
        super().__post_init__()
        check_range(self, "tau", 0.0, 1.0, lo_open=True)
        check_range(self, "expectile", 0.0, 1.0, lo_open=True, hi_open=True)
        check_range(self, "alpha", 0.0, math.inf)
        check_bool(self, "layer_norm")
        check_goal_source(self)
        check_actor_goals(self)


class GCIQL(Baseline):
    name = "gciql"
    config_class = GCIQLConfig

    def __init__(self, config=None, problem=None, progress=None):
        super().__init__(config, problem, progress)
        self.value_net = value_net(self.config, self.config.layer_norm)
        self.critic_net = value_net(self.config, self.config.layer_norm)
        self.optimizer = optax.adam(self.config.learning_rate)

    def init_model(self, key: jax.Array, spec: Spec) -> Any:
        kv, kq, kp = jax.random.split(key, 3)
        ex = spec.example()
        x, xa = observe(self.problem, ex.s, ex.g), observe_action(self.problem, ex.s, ex.g, ex.a)
        params = {"value": self.value_net.init(kv, x),
                  "critic": init_ensemble(self.critic_net, kq, xa),
                  "actor": actor_net(self.config, spec.action_dim).init(kp, x)}
        return {"params": params, "target_critic": params["critic"],
                "opt": self.optimizer.init(params)}

    def v(self, value: Any, s: jax.Array, g: jax.Array | None) -> jax.Array:
        """``V(s, g) [B]``."""
        return self.value_net.apply(value, observe(self.problem, s, g))[:, 0]

    def q(self, critic: Any, s: jax.Array, g: jax.Array | None, a: jax.Array) -> jax.Array:
        """``[2, B]``: both critics ``Q_i(s, a, g)``."""
        return apply_ensemble(self.critic_net, critic,
                              observe_action(self.problem, s, g, a))[..., 0]

    def value_loss(self, params: Any, target_critic: Any, b: Transitions):
        q = jnp.min(self.q(target_critic, b.s, b.g, b.a), axis=0)
        v = self.v(params["value"], b.s, b.g)
        value_loss = jnp.mean(expectile_loss(q - v, q - v, self.config.expectile))
        return value_loss, {"value_loss": value_loss, "v_mean": jnp.mean(v),
                            "v_max": jnp.max(v), "v_min": jnp.min(v)}

    def critic_loss(self, params: Any, b: Transitions):
        next_v = jax.lax.stop_gradient(self.v(params["value"], b.s_next, b.g))
        y = b.r + self.config.gamma * mask_of(b) * next_v
        q_i = self.q(params["critic"], b.s, b.g, b.a)
        critic_loss = jnp.mean(jnp.sum((q_i - y) ** 2, axis=0))
        return critic_loss, {"critic_loss": critic_loss, "q_mean": jnp.mean(y),
                             "q_max": jnp.max(y), "q_min": jnp.min(y)}

    def actor_loss(self, params: Any, b: Transitions):
        cfg, problem = self.config, self.problem
        mean = actor_mean(cfg, problem, params["actor"], b.s, b.g)
        q_actions = project(problem, mean)
        critic = jax.lax.stop_gradient(params["critic"])  # OGBench: the stored parameters
        q = jnp.min(self.q(critic, b.s, b.g, q_actions), axis=0)
        return ddpg_bc_loss(problem, cfg.alpha, mean, q, b.a)

    def batch(self, data, rows, key, n_valid):
        """``(value batch, actor batch)``: OGBench's goals from the trajectories, or the rows'."""
        cfg = self.config
        return minibatches(cfg.goals, data, rows, key, n_valid, cfg.gamma, self.name,
                           actor=actor_goals(cfg.actor_p_randomgoal))

    def loss(self, params: Any, target_critic: Any, b: Transitions,
             b_actor: Transitions | None = None) -> tuple[jax.Array, dict]:
        """``L_V + L_Q + L_pi`` (see the module docstring) and the metrics; ``b_actor``: the
        rows with the actor's goals (default ``b``)."""
        value_loss, value_info = self.value_loss(params, target_critic, b)
        critic_loss, critic_info = self.critic_loss(params, b)
        actor_loss, actor_info = self.actor_loss(params, b if b_actor is None else b_actor)
        return value_loss + critic_loss + actor_loss, {**value_info, **critic_info, **actor_info}

    def update(self, model, batch, key, step):
        """One Adam step; ``batch``: rows, or ``(value rows, actor rows)`` (:meth:`batch`)."""
        pair = (batch, batch) if isinstance(batch, Transitions) else batch
        grads, metrics = jax.grad(self.loss, has_aux=True)(model["params"],
                                                           model["target_critic"], *pair)
        updates, opt = self.optimizer.update(grads, model["opt"], model["params"])
        params = optax.apply_updates(model["params"], updates)
        # OGBench's target_update: the online parameters before this step's update
        target = polyak(model["target_critic"], model["params"]["critic"], self.config.tau)
        return {"params": params, "target_critic": target, "opt": opt}, metrics

    def actions(self, model, s, g):
        return project(self.problem,
                       actor_mean(self.config, self.problem, model["params"]["actor"], s, g))


def make(config: GCIQLConfig | None = None, problem: Problem | None = None,
         progress=None) -> GCIQL:
    """The GCIQL agent (``config`` None: OGBench's defaults, point-maze ``alpha``)."""
    return GCIQL(config, problem, progress)
