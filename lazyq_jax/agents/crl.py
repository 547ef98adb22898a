"""Contrastive RL (CRL) with a DDPG+BC actor, as OGBench's ``crl`` agent.

Eysenbach, Zhang, Salakhutdinov & Levine, "Contrastive Learning as Goal-Conditioned
Reinforcement Learning", NeurIPS 2022 (arXiv:2206.07568).  Implemented as OGBench's agent
(Park, Frans, Eysenbach & Levine, ICLR 2025), ``impls/agents/crl.py`` and
``GCBilinearValue`` in ``impls/utils/networks.py`` of github.com/seohongpark/ogbench (read at
commit 1d4140997f60), with its defaults (``actor_loss='ddpgbc'``, ``const_std=True``, two
critics) and its point-maze setting ``alpha = 0.03`` (``impls/hyperparameters.sh``; the
file's own default is 0.1).

The critic is bilinear: ``f_e(s, a, g) = phi_e(s, a) . psi_e(g) / sqrt(latent_dim)`` for the
two members ``e`` of an ensemble, ``phi`` and ``psi`` MLPs to ``latent_dim`` numbers.  It is
the logit of "``g`` is a future state of ``(s, a)``" against "``g`` is another row's", whose
optimum is the log of the discounted state-occupancy ratio: a Q-function up to a term in ``g``.

Losses, per step on one minibatch of ``B`` rows, summed and minimised by one Adam (``lr``
3e-4; no target networks, no rewards):

* critic (``CRLAgent.contrastive_loss``), binary NCE over the batch: row ``i``'s own goal
  ``g_i`` (a future state of its trajectory) is the positive, the other rows' goals the
  negatives::

      l_ije = phi_e(s_i, a_i) . psi_e(g_j) / sqrt(latent_dim)        # [B, B, 2]
      L_f   = mean_ije BCE(sigmoid(l_ije), 1[i = j])

* actor, DDPG+BC (``actor_loss``), the critics not differentiated (OGBench: the stored
  parameters), as GCIQL's with ``Q = min_e f_e``::

      a_pi  = clip(mean(s, g))
      Q_pi  = min_e f_e(s, a_pi, g)
      L_pi  = -E[Q_pi] / sg(E|Q_pi| + 1e-6) - alpha E[ log pi(a | s, g) ]

Goals, as OGBench's CRL: the critic's goals a later state of the row's trajectory at a
geometric offset (``value_p_trajgoal = 1``, ``value_geom_sample``: the positive pairs), the
actor's a uniform later state (``actor_p_trajgoal = 1``; with ``actor_p_randomgoal = p``,
OGBench's stitch setting 0.5, a random state with ``p``), drawn every minibatch
(:mod:`lazyq_jax.agents.goals`, ``goals="auto"``); on data without trajectories (or
``goals="rows"``) each row's own goal serves both, which is CRL only where those goals are
states the row's trajectory reaches later.  Goals must be states (``g[N, d_s]``).

Networks: ``phi``, ``psi`` are OGBench's MLP (``depth - 1`` hidden layers of ``width``:
Dense, GELU, LayerNorm if ``layer_norm``; a linear output of ``latent_dim``), each a stacked
pair (:func:`~lazyq_jax.agents.common.init_ensemble`; OGBench's ``ensemblize``, the same
distribution); the actor is GCBC's Gaussian ``N(c u, c)`` (:mod:`lazyq_jax.agents.gcbc`),
acting with its mode projected onto the action set.  Deviations from OGBench: ``phi``'s states and
``psi``'s goals (states) enter divided by ``problem.state_scale``, the actor's ``(s, g)`` as
:func:`~lazyq_jax.agents.common.observe` encodes them for every goal-conditioned agent here
(the goal as it is: the same where the scale is 1, as on the point maze), and actions in
units of ``c = problem.action_length`` (OGBench's are already in ``[-1, 1]``); steps from
``BaselineConfig.steps`` (OGBench 1M).  Only DDPG+BC (OGBench's AWR option, which adds a
contrastive ``V``, is not offered); no discrete actions, no visual encoders.
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
    observe,
    project,
    require_state_goals,
    scaled_states,
)
from lazyq_jax.agents.gcbc import GCMLP, actor_mean, actor_net
from lazyq_jax.agents.gciql import ddpg_bc_loss
from lazyq_jax.agents.gcivl import check_bool
from lazyq_jax.agents.goals import (
    GoalMix,
    actor_goals,
    check_actor_goals,
    check_goal_source,
    minibatches,
)
from lazyq_jax.types import Transitions

# OGBench's CRL critic goals: a later state of the same trajectory at a geometric offset
FUTURE_GOALS = GoalMix(p_cur=0.0, p_traj=1.0, geom=True)


@dataclasses.dataclass(frozen=True)
class CRLConfig(BaselineConfig):
    """:class:`BaselineConfig` with OGBench's ``crl`` defaults (``batch_size`` 1024,
    ``learning_rate`` 3e-4, ``width`` 512 x ``depth`` 4 = hidden (512, 512, 512) and the output
    layer, ``gamma`` 0.99: the discount of the geometric goal offsets) plus ``latent_dim``
    (512), ``alpha`` (the BC weight of DDPG+BC: OGBench's point-maze 0.03, its file default
    0.1; >= 0) and ``layer_norm`` (in ``phi`` and ``psi``, True).
    ``goals``: ``"auto"`` (default) OGBench's fresh goals from the trajectories when the data
    have them, else the rows' own goals; ``"trajectories"`` (required) or ``"rows"``.
    ``actor_p_randomgoal``: OGBench's actor goals (:func:`~lazyq_jax.agents.goals.actor_goals`):
    a random state with this probability, else a uniform later state of the row's trajectory
    (0, OGBench's default; 0.5 its stitch datasets' setting, ``impls/hyperparameters.sh``; in
    ``[0, 1]``; above 0 needs goals from the trajectories)."""

    batch_size: int = 1024
    learning_rate: float = 3e-4
    width: int = 512
    depth: int = 4
    gamma: float = 0.99
    latent_dim: int = 512
    alpha: float = 0.03
    layer_norm: bool = True
    goals: str = "auto"
    actor_p_randomgoal: float = 0.0

    def __post_init__(self) -> None:
        super().__post_init__()
        check_int(self, "latent_dim", 1)
        check_range(self, "alpha", 0.0, math.inf)
        check_bool(self, "layer_norm")
        check_goal_source(self)
        check_actor_goals(self)


class CRL(Baseline):
    name = "crl"
    config_class = CRLConfig

    def __init__(self, config=None, problem=None, progress=None):
        super().__init__(config, problem, progress)
        cfg = self.config
        self.phi_net = GCMLP(cfg.width, cfg.depth, cfg.latent_dim, layer_norm=cfg.layer_norm)
        self.psi_net = GCMLP(cfg.width, cfg.depth, cfg.latent_dim, layer_norm=cfg.layer_norm)
        self.optimizer = optax.adam(cfg.learning_rate)

    def check_data(self, spec: Spec) -> None:
        """Goals must be states (the critic tells a row's future states from other rows')."""
        require_state_goals(spec, "crl", "contrasts a row's future states with other rows'")

    def init_model(self, key: jax.Array, spec: Spec) -> Any:
        self.check_data(spec)
        k_phi, k_psi, k_actor = jax.random.split(key, 3)
        ex = spec.example()
        params = {"phi": init_ensemble(self.phi_net, k_phi, self.state_action(ex.s, ex.a)),
                  "psi": init_ensemble(self.psi_net, k_psi, self.scaled(ex.g)),
                  "actor": actor_net(self.config, spec.action_dim).init(
                      k_actor, observe(self.problem, ex.s, ex.g))}
        return {"params": params, "opt": self.optimizer.init(params)}

    # --- the critic
    def scaled(self, s: jax.Array) -> jax.Array:
        return scaled_states(self.problem, s)

    def state_action(self, s: jax.Array, a: jax.Array) -> jax.Array:
        """``phi``'s input: the scaled state and the action in units of ``c``."""
        return jnp.concatenate([self.scaled(s), jnp.asarray(a, jnp.float32) / self.problem.action_length], -1)

    def representations(self, params: Any, s: jax.Array, a: jax.Array, g: jax.Array):
        """``(phi [2, B, latent], psi [2, B, latent])`` of both critics."""
        return (apply_ensemble(self.phi_net, params["phi"], self.state_action(s, a)),
                apply_ensemble(self.psi_net, params["psi"], self.scaled(g)))

    def critic(self, params: Any, s: jax.Array, g: jax.Array, a: jax.Array) -> jax.Array:
        """``[2, B]``: both critics ``f_e(s, a, g)`` (OGBench's ``GCBilinearValue``)."""
        phi, psi = self.representations(params, s, a, g)
        return jnp.sum(phi * psi, axis=-1) / math.sqrt(self.config.latent_dim)

    # --- losses
    def contrastive_loss(self, params: Any, b: Transitions):
        phi, psi = self.representations(params, b.s, b.a, b.g)
        logits = jnp.einsum("eik,ejk->ije", phi, psi) / math.sqrt(self.config.latent_dim)
        eye = jnp.eye(b.s.shape[0], dtype=logits.dtype)
        loss = jnp.mean(optax.sigmoid_binary_cross_entropy(logits, eye[:, :, None]))
        mean_logits = jnp.mean(logits, axis=-1)
        off = 1.0 - eye
        return loss, {"contrastive_loss": loss,
                      "binary_accuracy": jnp.mean((mean_logits > 0) == (eye > 0)),
                      "categorical_accuracy": jnp.mean(
                          jnp.argmax(mean_logits, axis=1) == jnp.arange(b.s.shape[0])),
                      "logits_pos": jnp.sum(mean_logits * eye) / jnp.sum(eye),
                      "logits_neg": jnp.sum(mean_logits * off) / jnp.maximum(jnp.sum(off), 1.0)}

    def actor_loss(self, params: Any, b: Transitions):
        cfg, problem = self.config, self.problem
        mean = actor_mean(cfg, problem, params["actor"], b.s, b.g)
        q_actions = project(problem, mean)
        frozen = jax.lax.stop_gradient({k: v for k, v in params.items() if k != "actor"})
        q = jnp.min(self.critic(frozen, b.s, b.g, q_actions), axis=0)
        return ddpg_bc_loss(problem, cfg.alpha, mean, q, b.a)

    def loss(self, params: Any, b: Transitions, b_actor: Transitions | None = None
             ) -> tuple[jax.Array, dict]:
        """``L_f + L_pi`` (module docstring) and the metrics; ``b``: the rows with the critic's
        goals, ``b_actor``: with the actor's goals (default ``b``)."""
        critic_loss, critic_info = self.contrastive_loss(params, b)
        actor_loss, actor_info = self.actor_loss(params, b if b_actor is None else b_actor)
        return critic_loss + actor_loss, {**critic_info, **actor_info}

    def batch(self, data, rows, key, n_valid):
        """``(critic batch, actor batch)``: OGBench's CRL goals (a geometric and a uniform later
        state of the trajectory) from the trajectories, or the rows' own goals."""
        return minibatches(self.config.goals, data, rows, key, n_valid, self.config.gamma,
                           self.name, value=FUTURE_GOALS,
                           actor=actor_goals(self.config.actor_p_randomgoal))

    def update(self, model, batch, key, step):
        """One Adam step; ``batch``: rows, or ``(critic rows, actor rows)`` (:meth:`batch`)."""
        pair = (batch, batch) if isinstance(batch, Transitions) else batch
        grads, metrics = jax.grad(self.loss, has_aux=True)(model["params"], *pair)
        updates, opt = self.optimizer.update(grads, model["opt"], model["params"])
        return {"params": optax.apply_updates(model["params"], updates), "opt": opt}, metrics

    def actions(self, model, s, g):
        return project(self.problem,
                       actor_mean(self.config, self.problem, model["params"]["actor"], s, g))


def make(config: CRLConfig | None = None, problem: Problem | None = None,
         progress=None) -> CRL:
    """The CRL agent (``config`` None: OGBench's defaults, point-maze ``alpha``)."""
    return CRL(config, problem, progress)
