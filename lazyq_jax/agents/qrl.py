"""Quasimetric RL (QRL) with an IQE value and a latent-dynamics DDPG+BC actor, as OGBench's
``qrl`` agent.

Wang, Torralba, Isola & Zhang, "Optimal Goal-Reaching Reinforcement Learning via Quasimetric
Learning", ICML 2023 (arXiv:2304.01203); the interval quasimetric embedding (IQE) is Wang &
Isola, "Improved Representation of Asymmetrical Distances with Interval Quasimetric
Embeddings", 2022 (arXiv:2211.15120).  Implemented as OGBench's agent (Park, Frans,
Eysenbach & Levine, ICLR 2025), ``impls/agents/qrl.py`` and ``GCIQEValue`` in
``impls/utils/networks.py`` of github.com/seohongpark/ogbench (read at commit
1d4140997f60), with its defaults (``quasimetric_type='iqe'``, ``actor_loss='ddpgbc'``) and
its point-maze setting ``alpha = 0.0003`` (``impls/hyperparameters.sh``).

The value is a learned quasimetric ``d(s, g) >= 0`` (steps to go; ``V = -d``):
``phi`` an MLP from a state to ``latent_dim`` numbers, cut into groups of ``components``;
in each group the union of the intervals ``[x_i, y_i]`` with ``x_i < y_i`` (``x = phi(s)``,
``y = phi(g)``) has a length :func:`iqe_components`, and
``d = a mean(lengths) + (1 - a) max(lengths)`` with ``a = sigmoid(a_raw)`` learned
(:func:`iqe`).  ``d(x, x) = 0`` and the triangle inequality hold for any ``phi``.

Losses, per step on one minibatch, summed and minimised by one Adam (``lr`` 3e-4; no target
networks):

* value (``QRLAgent.value_loss``), a Lagrangian: push the distances to random goals up and
  keep every transition's distance below one step::

      d_neg   = d(s, g_random)                   d_pos = d(s, s')
      L_neg   = E[ 100 softplus(5 - d_neg / 100) ]        # the original code's shaping
      L_pos   = E[ relu(d_pos - 1)^2 ]
      L_V     = L_neg + sg(lam) L_pos
      L_lam   = lam (eps - sg(L_pos))                      # lam = exp(log_lam), eps 0.05

* latent dynamics (``dynamics_loss``), which also trains ``phi``::

      z       = phi(s),  z' = phi(s'),  z^ = z + f(z, a / c)
      L_f     = E[ d_z(z', z^) + d_z(z^, z') ] / 2        # d_z: the IQE on latents

* actor, DDPG+BC through the latent dynamics (``actor_loss``), ``phi``, ``f`` and the IQE
  not differentiated (OGBench: the stored parameters)::

      a_pi    = clip(mean(s, g))
      Q_pi    = -d_z(phi(s) + f(phi(s), a_pi / c), phi(g))
      L_pi    = -E[Q_pi] / sg(E|Q_pi| + 1e-6) - alpha E[ log pi(a | s, g) ]

Goals, as OGBench's QRL: the value goals are random dataset states
(``value_p_randomgoal = 1``; the rows' rewards and ``done`` are never used), the actor goals a
uniform future state of the same trajectory (``actor_p_trajgoal = 1``; with
``actor_p_randomgoal = p``, OGBench's stitch setting 0.5, a random state with ``p``), drawn every minibatch
(:mod:`lazyq_jax.agents.goals`, ``goals="auto"``); on data without trajectories (or
``goals="rows"``) each row's own goal serves both.  Goals must be states (``g[N, d_s]``): the
quasimetric compares two states.

Networks: ``phi`` and ``f`` are OGBench's MLP (``depth - 1`` hidden layers of ``width``:
Dense, GELU, LayerNorm if ``layer_norm``; a linear output of ``latent_dim``); the actor is
GCBC's Gaussian ``N(c u, c)`` (:mod:`lazyq_jax.agents.gcbc`; log-likelihood
:func:`~lazyq_jax.agents.common.log_likelihood`, OGBench's up to a constant), acting with its
mode projected onto the action set.  Deviations from OGBench: ``phi``'s input is the state
divided by ``problem.state_scale`` (goals too: they are states); actions enter ``f`` in units of
``c = problem.action_length`` (OGBench's are already in ``[-1, 1]``); steps from
``BaselineConfig.steps`` (OGBench 1M).  Only IQE and DDPG+BC (OGBench's defaults; its MRN and
AWR options are not offered); no discrete actions, no visual encoders.
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
    check,
    check_int,
    check_range,
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

# OGBench's QRL value goals: a random dataset state always
RANDOM_GOALS = GoalMix(p_cur=0.0, p_traj=0.0, geom=True)

# ----------------------------------------------------------------------------- the quasimetric


def _ends_before(xs: jax.Array, ys: jax.Array) -> jax.Array:
    """``[..., i, j]``: the end ``y_j`` of each valid interval ``j`` that starts before interval
    ``i`` (at ``x_j < x_i``, or at ``x_j = x_i`` with ``j < i``), else ``-inf``."""
    index = jnp.arange(xs.shape[-1])
    xi, xj = xs[..., :, None], xs[..., None, :]
    before = (xj < xi) | ((xj == xi) & (index[None, :] < index[:, None]))
    return jnp.where(before & (xs < ys)[..., None, :], ys[..., None, :], -jnp.inf)


def iqe_components(x: jax.Array, y: jax.Array, components: int) -> jax.Array:
    """``[..., latent / components]``: per group of ``components`` numbers the length of the
    union of the intervals ``[x_i, y_i]`` where ``x_i < y_i`` (empty where ``x_i >= y_i``).

    The value of OGBench's ``GCIQEValue`` computed without a sort: taken in the order of their
    starts (ties by index), each valid interval adds the part of it beyond the farthest end
    ``R_i`` of the valid intervals before it, ``relu(y_i - max(x_i, R_i))``; what the earlier
    intervals cover of ``[x_i, y_i]`` is exactly ``[x_i, min(R_i, y_i)]``, since each of them
    starts at or before ``x_i``.  ``O(components^2)`` comparisons a group, all elementwise;
    ``R_i`` is a gather of the arg-max, so that autodiff's gradient is a gather's, not a max's
    over the whole table.  A QRL step at the point maze's sizes ran 4.3x faster than with
    OGBench's sort (``experiments/bench_qrl.py``; same values and gradients, tests/test_qrl.py)."""
    xs = jnp.reshape(x, (*x.shape[:-1], -1, components))
    ys = jnp.reshape(y, (*y.shape[:-1], -1, components))
    ends = _ends_before(xs, ys)
    farthest = jnp.argmax(ends, axis=-1)
    reach = jnp.where(jnp.any(ends > -jnp.inf, axis=-1),
                      jnp.take_along_axis(ys, farthest, axis=-1), -jnp.inf)
    added = jnp.where(xs < ys, jax.nn.relu(ys - jnp.maximum(xs, reach)), 0.0)
    return jnp.sum(added, axis=-1)


def iqe_components_sorted(x: jax.Array, y: jax.Array, components: int) -> jax.Array:
    """:func:`iqe_components` as OGBench's ``GCIQEValue`` computes it (``impls/utils/networks.py``
    at 1d4140997f60, verbatim up to names): the ``2 components`` end points sorted, each one's
    change of the number of open intervals summed along that order, and the gaps inside an
    interval added up.  The reference the tests and ``experiments/bench_qrl.py`` compare
    against; ~4x slower in a QRL step on the CPU (XLA's sort)."""
    x = jnp.reshape(x, (*x.shape[:-1], -1, components))
    y = jnp.reshape(y, (*y.shape[:-1], -1, components))
    valid = x < y
    xy = jnp.concatenate(jnp.broadcast_arrays(x, y), axis=-1)
    ixy = xy.argsort(axis=-1)
    sxy = jnp.take_along_axis(xy, ixy, axis=-1)
    neg_inc_copies = (jnp.take_along_axis(valid, ixy % components, axis=-1)
                      * jnp.where(ixy < components, -1, 1))
    neg_inp_copies = jnp.cumsum(neg_inc_copies, axis=-1)
    neg_f = -1.0 * (neg_inp_copies < 0)
    neg_incf = jnp.concatenate([neg_f[..., :1], neg_f[..., 1:] - neg_f[..., :-1]], axis=-1)
    return (sxy * neg_incf).sum(axis=-1)


def iqe(x: jax.Array, y: jax.Array, alpha_raw: jax.Array, components: int) -> jax.Array:
    """The IQE distance ``[...]`` from latent ``x`` to latent ``y``: ``a mean + (1 - a) max``
    of :func:`iqe_components` with ``a = sigmoid(alpha_raw)`` (OGBench's ``GCIQEValue``)."""
    lengths = iqe_components(x, y, components)
    a = jax.nn.sigmoid(alpha_raw)
    return a * jnp.mean(lengths, axis=-1) + (1.0 - a) * jnp.max(lengths, axis=-1)


# ----------------------------------------------------------------------------- the agent


@dataclasses.dataclass(frozen=True)
class QRLConfig(BaselineConfig):
    """:class:`BaselineConfig` with OGBench's ``qrl`` defaults (``batch_size`` 1024,
    ``learning_rate`` 3e-4, ``width`` 512 x ``depth`` 4 = hidden (512, 512, 512) and the output
    layer, ``gamma`` 0.99: only the discount of geometric goal offsets, unused by QRL's goals)
    plus ``latent_dim`` (512), ``components`` (IQE's ``dim_per_component``, 8; must divide
    ``latent_dim``), ``eps`` (the transitions' margin of the dual, 0.05, > 0), ``alpha`` (the
    BC weight of DDPG+BC: OGBench's point-maze 0.0003, its file default 0.003; >= 0) and
    ``layer_norm`` (in ``phi`` and the dynamics, True).
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
    components: int = 8
    eps: float = 0.05
    alpha: float = 0.0003
    layer_norm: bool = True
    goals: str = "auto"
    actor_p_randomgoal: float = 0.0

    def __post_init__(self) -> None:
        super().__post_init__()
        check_int(self, "latent_dim", 1)
        check_int(self, "components", 1)
        check(self.latent_dim % self.components == 0,
              f"QRLConfig.latent_dim ({self.latent_dim}) must be a multiple of components "
              f"({self.components}): the IQE cuts the latent into groups of that size")
        check_range(self, "eps", 0.0, math.inf, lo_open=True)
        check_range(self, "alpha", 0.0, math.inf)
        check_bool(self, "layer_norm")
        check_goal_source(self)
        check_actor_goals(self)


class QRL(Baseline):
    name = "qrl"
    config_class = QRLConfig

    def __init__(self, config=None, problem=None, progress=None):
        super().__init__(config, problem, progress)
        cfg = self.config
        self.phi_net = GCMLP(cfg.width, cfg.depth, cfg.latent_dim, layer_norm=cfg.layer_norm)
        self.dynamics_net = GCMLP(cfg.width, cfg.depth, cfg.latent_dim, layer_norm=cfg.layer_norm)
        self.optimizer = optax.adam(cfg.learning_rate)

    def check_data(self, spec: Spec) -> None:
        """Goals must be states (the quasimetric compares two states)."""
        require_state_goals(spec, "qrl", "learns a quasimetric between states")

    def init_model(self, key: jax.Array, spec: Spec) -> Any:
        self.check_data(spec)
        k_phi, k_dyn, k_actor = jax.random.split(key, 3)
        ex = spec.example()
        z = jnp.zeros((1, self.config.latent_dim + spec.action_dim), jnp.float32)
        params = {"phi": self.phi_net.init(k_phi, self.scaled(ex.s)),
                  "alpha_raw": jnp.zeros((), jnp.float32),   # OGBench's Param(): sigmoid(0) = 0.5
                  "log_lam": jnp.zeros((), jnp.float32),     # LogParam(init_value=1)
                  "dynamics": self.dynamics_net.init(k_dyn, z),
                  "actor": actor_net(self.config, spec.action_dim).init(
                      k_actor, observe(self.problem, ex.s, ex.g))}
        return {"params": params, "opt": self.optimizer.init(params)}

    # --- the quasimetric
    def scaled(self, s: jax.Array) -> jax.Array:
        return scaled_states(self.problem, s)

    def latent(self, params: Any, s: jax.Array) -> jax.Array:
        """``phi(s) [B, latent_dim]``."""
        return self.phi_net.apply(params["phi"], self.scaled(s))

    def latent_distance(self, params: Any, z: jax.Array, w: jax.Array) -> jax.Array:
        return iqe(z, w, params["alpha_raw"], self.config.components)

    def distance(self, params: Any, s: jax.Array, g: jax.Array) -> jax.Array:
        """``d(s, g) [B]``: the learned steps from state ``s`` to goal state ``g``."""
        return self.latent_distance(params, self.latent(params, s), self.latent(params, g))

    def next_latent(self, params: Any, z: jax.Array, a: jax.Array) -> jax.Array:
        """The latent dynamics ``z + f(z, a / c)``."""
        x = jnp.concatenate([z, jnp.asarray(a, jnp.float32) / self.problem.action_length], -1)
        return z + self.dynamics_net.apply(params["dynamics"], x)

    # --- losses
    def value_loss(self, params: Any, b: Transitions):
        cfg = self.config
        d_neg = self.distance(params, b.s, b.g)
        d_pos = self.distance(params, b.s, b.s_next)
        lam = jnp.exp(params["log_lam"])
        d_neg_loss = jnp.mean(100.0 * jax.nn.softplus(5.0 - d_neg / 100.0))
        d_pos_loss = jnp.mean(jax.nn.relu(d_pos - 1.0) ** 2)
        value_loss = d_neg_loss + d_pos_loss * jax.lax.stop_gradient(lam)
        lam_loss = lam * (cfg.eps - jax.lax.stop_gradient(d_pos_loss))
        return value_loss + lam_loss, {
            "value_loss": value_loss, "lam_loss": lam_loss, "lam": lam,
            "d_neg_loss": d_neg_loss, "d_neg_mean": jnp.mean(d_neg), "d_neg_max": jnp.max(d_neg),
            "d_pos_loss": d_pos_loss, "d_pos_mean": jnp.mean(d_pos), "d_pos_max": jnp.max(d_pos)}

    def dynamics_loss(self, params: Any, b: Transitions):
        z, z_next = self.latent(params, b.s), self.latent(params, b.s_next)
        pred = self.next_latent(params, z, b.a)
        loss = jnp.mean(self.latent_distance(params, z_next, pred)
                        + self.latent_distance(params, pred, z_next)) / 2.0
        return loss, {"dynamics_loss": loss}

    def actor_loss(self, params: Any, b: Transitions):
        cfg, problem = self.config, self.problem
        mean = actor_mean(cfg, problem, params["actor"], b.s, b.g)
        q_actions = project(problem, mean)
        frozen = jax.lax.stop_gradient({k: v for k, v in params.items() if k != "actor"})
        z, z_goal = self.latent(frozen, b.s), self.latent(frozen, b.g)
        q = -self.latent_distance(frozen, self.next_latent(frozen, z, q_actions), z_goal)
        return ddpg_bc_loss(problem, cfg.alpha, mean, q, b.a)

    def loss(self, params: Any, b: Transitions, b_actor: Transitions | None = None
             ) -> tuple[jax.Array, dict]:
        """``L_V + L_lam + L_f + L_pi`` (module docstring) and the metrics; ``b``: the rows with
        the value goals, ``b_actor``: with the actor's goals (default ``b``)."""
        value_loss, value_info = self.value_loss(params, b)
        dynamics_loss, dynamics_info = self.dynamics_loss(params, b)
        actor_loss, actor_info = self.actor_loss(params, b if b_actor is None else b_actor)
        return (value_loss + dynamics_loss + actor_loss,
                {**value_info, **dynamics_info, **actor_info})

    def batch(self, data, rows, key, n_valid):
        """``(value batch, actor batch)``: OGBench's QRL goals (random states; a uniform future
        state) from the trajectories, or the rows' own goals."""
        return minibatches(self.config.goals, data, rows, key, n_valid, self.config.gamma,
                           self.name, value=RANDOM_GOALS,
                           actor=actor_goals(self.config.actor_p_randomgoal))

    def update(self, model, batch, key, step):
        """One Adam step; ``batch``: rows, or ``(value rows, actor rows)`` (:meth:`batch`)."""
        pair = (batch, batch) if isinstance(batch, Transitions) else batch
        grads, metrics = jax.grad(self.loss, has_aux=True)(model["params"], *pair)
        updates, opt = self.optimizer.update(grads, model["opt"], model["params"])
        return {"params": optax.apply_updates(model["params"], updates), "opt": opt}, metrics

    def actions(self, model, s, g):
        return project(self.problem,
                       actor_mean(self.config, self.problem, model["params"]["actor"], s, g))

    def value_fn(self, state):
        """``V(s, g) = -d(s, g)`` of a trained (unstacked) state, in steps (the runner draws it
        as it draws lazy Q's)."""
        params = state.model["params"]
        return lambda s, g: -self.distance(params, s, g)


def make(config: QRLConfig | None = None, problem: Problem | None = None,
         progress=None) -> QRL:
    """The QRL agent (``config`` None: OGBench's defaults, point-maze ``alpha``)."""
    return QRL(config, problem, progress)
