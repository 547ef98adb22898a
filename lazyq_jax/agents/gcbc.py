"""Goal-conditioned behaviour cloning (GCBC), as OGBench's ``gcbc`` agent.

Park, Frans, Eysenbach & Levine, "OGBench: Benchmarking Offline Goal-Conditioned RL",
ICLR 2025 (arXiv:2410.20092), agent ``impls/agents/gcbc.py`` and networks
``impls/utils/networks.py`` of github.com/seohongpark/ogbench (read at commit
1d4140997f60); the method is goal-conditioned supervised imitation (Lynch et al. 2019;
Ghosh et al., "Learning to Reach Goals via Iterated Supervised Learning", ICLR 2021).

Loss (``GCBCAgent.actor_loss``: ``log_prob = dist.log_prob(batch['actions'])``,
``actor_loss = -log_prob.mean()``), maximum likelihood of the data's actions::

    L_pi = -E_(s, a, g) [ log pi(a | s, g) ]

one Adam step per minibatch (``lr`` 3e-4, ``batch_size`` 1024).

The actor (OGBench's ``GCActor`` with ``state_dependent_std=False, const_std=True,
tanh_squash=False``; this module's :class:`GCMLP` and :func:`actor_mean`): an MLP of
``depth - 1`` hidden layers of ``width`` units (Dense, GELU; no LayerNorm in OGBench's
actor) and a linear head ``u[n_a]`` initialised at scale 1e-2; the policy is the
Gaussian ``N(mean = c u, std = c)`` per component (OGBench: ``N(u, 1)`` on actions in
``[-1, 1]``; ``c = problem.action_length`` converts units), no tanh squash.  The
log-likelihood is :func:`~lazyq_jax.agents.common.log_likelihood` of this fixed
concentration: in the box ``-|(c u - a) / c|^2 / 2``, which is OGBench's
``MultivariateNormalDiag(u, 1).log_prob(a / c)`` plus the constant
``n_a / 2 log(2 pi)`` (same gradients; the reported ``bc_log_prob`` is ours, without
the constant).  On the sphere (``action_set = "ball"``, not in OGBench) it is the
von Mises-Fisher log-likelihood ``cos(u, a)`` (``kappa = 1``) of the direction of the
mean; its maximum-likelihood direction is that of the (weighted) mean action, as the
Gaussian's.  Acting is the mode, as OGBench's evaluation (``eval_temperature = 0``):
the mean projected onto the action set (:func:`~lazyq_jax.agents.common.project`: the
box clip OGBench applies, ``clip(c u, -c, c)``; on the sphere ``c u / |u|``).

Goals, as OGBench's GCBC: on trajectory data (``Transitions.traj_last``, e.g. the point
maze) every minibatch draws fresh actor goals, a uniform future state of the same
trajectory (``actor_p_trajgoal = 1``; :mod:`lazyq_jax.agents.goals`, ``goals="auto"``); on
other data (or ``goals="rows"``) each row's own goal.  Deviations from OGBench.  Inputs are
:func:`~lazyq_jax.agents.common.observe` (states divided by ``problem.state_scale``,
angle goals as ``cos, sin``, vector goals as they are); OGBench concatenates the raw
observation and goal.  The number of steps is ``BaselineConfig.steps`` (OGBench 1M).
No discrete actions, no visual encoders.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import optax

from lazyq_jax.agents.base import Problem, Spec
from lazyq_jax.agents.common import Baseline, BaselineConfig, log_likelihood, observe, project
from lazyq_jax.agents.goals import check_goal_source, minibatches
from lazyq_jax.types import Transitions

# ----------------------------------------------------------------------------- networks


def default_init(scale: float = 1.0):
    """OGBench's kernel initialiser (``networks.default_init``): variance scaling,
    ``fan_avg``, uniform."""
    return nn.initializers.variance_scaling(scale, "fan_avg", "uniform")


class GCMLP(nn.Module):
    """OGBench's ``MLP`` (``impls/utils/networks.py``) in our ``width``/``depth`` terms:
    ``depth - 1`` hidden layers ``Dense(width)``, GELU, then LayerNorm if
    ``layer_norm`` (OGBench normalises after the activation), and a linear
    ``Dense(out)``; kernels by :func:`default_init` (the last at ``out_scale``: 1 for
    values, 1e-2 for the actor's mean head, OGBench's ``final_fc_init_scale``)."""

    width: int
    depth: int
    out: int
    layer_norm: bool = True
    out_scale: float = 1.0

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        for _ in range(self.depth - 1):
            x = nn.Dense(self.width, kernel_init=default_init())(x)
            x = nn.gelu(x)
            if self.layer_norm:
                x = nn.LayerNorm()(x)
        return nn.Dense(self.out, kernel_init=default_init(self.out_scale))(x)


def value_net(config: BaselineConfig, layer_norm: bool) -> GCMLP:
    """A value or critic network (``GCValue``): ``width`` x ``depth``, one output."""
    return GCMLP(config.width, config.depth, 1, layer_norm=layer_norm)


def actor_net(config: BaselineConfig, action_dim: int) -> GCMLP:
    """The actor's mean network (``GCActor``'s ``actor_net`` + ``mean_net``): no
    LayerNorm, head initialised at scale 1e-2."""
    return GCMLP(config.width, config.depth, action_dim, layer_norm=False, out_scale=1e-2)


def actor_mean(config: BaselineConfig, problem: Problem, params: Any, s: jax.Array,
               g: jax.Array | None) -> jax.Array:
    """The Gaussian's mean ``c u [B, n_a]`` (not projected; ``n_a`` read from ``params``)."""
    n_a = params["params"][f"Dense_{config.depth - 1}"]["kernel"].shape[-1]
    u = actor_net(config, n_a).apply(params, observe(problem, s, g))
    return problem.action_length * u


def actor_stats(problem: Problem, mean: jax.Array, a: jax.Array) -> dict:
    """OGBench's actor diagnostics: ``mse`` of the mean in units of ``c``."""
    return {"mse": jnp.mean(((mean - a) / problem.action_length) ** 2)}


# ----------------------------------------------------------------------------- the agent


@dataclasses.dataclass(frozen=True)
class GCBCConfig(BaselineConfig):
    """:class:`BaselineConfig` with OGBench's ``gcbc`` defaults: ``batch_size`` 1024,
    ``learning_rate`` 3e-4, ``width`` 512 x ``depth`` 4 (hidden dims (512, 512, 512)
    and the output layer); ``gamma`` (0.99, OGBench's ``discount``) is unused.
    ``goals``: where the goals of a minibatch come from: ``"auto"`` (default) OGBench's
    fresh value and actor goals from the trajectories when the data have them
    (``Transitions.traj_last``, :mod:`lazyq_jax.agents.goals`), else the rows' own goals;
    ``"trajectories"`` (required) or ``"rows"``.
    GCBC uses the actor goals only."""

    batch_size: int = 1024
    learning_rate: float = 3e-4
    width: int = 512
    depth: int = 4
    gamma: float = 0.99
    goals: str = "auto"

    def __post_init__(self) -> None:
        super().__post_init__()
        check_goal_source(self)


class GCBC(Baseline):
    name = "gcbc"
    config_class = GCBCConfig

    def __init__(self, config=None, problem=None, progress=None):
        super().__init__(config, problem, progress)
        self.optimizer = optax.adam(self.config.learning_rate)

    def init_model(self, key: jax.Array, spec: Spec) -> Any:
        ex = spec.example()
        params = {"actor": actor_net(self.config, spec.action_dim).init(
            key, observe(self.problem, ex.s, ex.g))}
        return {"params": params, "opt": self.optimizer.init(params)}

    def batch(self, data, rows, key, n_valid):
        """The rows with OGBench's actor goals (a uniform future state), or their own goals."""
        return minibatches(self.config.goals, data, rows, key, n_valid, self.config.gamma,
                           self.name)[1]

    def loss(self, params: Any, b: Transitions) -> tuple[jax.Array, dict]:
        """``-E[log pi(a | s, g)]`` and its metrics."""
        mean = actor_mean(self.config, self.problem, params["actor"], b.s, b.g)
        log_prob = log_likelihood(self.problem, mean, b.a)
        actor_loss = -jnp.mean(log_prob)
        return actor_loss, {"actor_loss": actor_loss, "bc_log_prob": jnp.mean(log_prob),
                            **actor_stats(self.problem, mean, b.a)}

    def update(self, model, batch, key, step):
        grads, metrics = jax.grad(self.loss, has_aux=True)(model["params"], batch)
        updates, opt = self.optimizer.update(grads, model["opt"], model["params"])
        return {"params": optax.apply_updates(model["params"], updates), "opt": opt}, metrics

    def actions(self, model, s, g):
        return project(self.problem,
                       actor_mean(self.config, self.problem, model["params"]["actor"], s, g))


def make(config: GCBCConfig | None = None, problem: Problem | None = None,
         progress=None) -> GCBC:
    """The GCBC agent (``config`` None: OGBench's defaults)."""
    return GCBC(config, problem, progress)
