"""Double DQN over a codebook of actions, with an optional discrete CQL(H) penalty.

Double DQN: van Hasselt, Guez & Silver, "Deep Reinforcement Learning with Double
Q-learning", AAAI 2016 (on Mnih et al., Nature 2015).  CQL(H): Kumar, Zhou, Tucker &
Levine, "Conservative Q-Learning for Offline Reinforcement Learning", NeurIPS 2020,
Eq. 4 (the discrete-action form of its published code).

The action set is replaced by a codebook of ``K`` actions (:func:`codebook`, kept in the
state so that a restored policy acts with the codebook it was trained with); a dataset
action counts as its nearest codeword.  The network outputs ``Q(s, g, k)`` for all
``K`` codewords.

* ``"ball"``: ``K`` directions on the sphere ``S^(n_a - 1)`` times ``c``.  ``n_a = 2``: the
  bins ``theta_k = 2 pi k / K`` on the circle; ``n_a = 3``: a Fibonacci lattice
  (``z_k = 1 - (2k + 1) / K``, longitudes in steps of the golden angle); ``n_a >= 4``:
  spherical k-means (20 Lloyd iterations in float32 on ``16 K`` uniform points of a
  fixed seed); ``n_a = 1``: ``{-c, c}``.  ``bins = None`` (default) takes ``K`` by ``n_a``
  (:data:`DEFAULT_DIRECTIONS`).  The covering radius (the worst angle from a direction
  to its nearest codeword) was measured numerically as the largest angle found: the max
  over 2 x 2 million random unit vectors, and local ascent from the 2000 worst of
  another million (a lower estimate of the true radius, tight to a few tenths of a
  degree); the tests check that 200,000 random directions stay within the bound:

  =====  ======  ===========  =====
  n_a    K       found (deg)  bound
  =====  ======  ===========  =====
  2      16      11.25        11.3  (exactly pi / K)
  3      128     13.8         14.5
  4      512     19.9         20.5
  5      2048    20.9         21.5
  6      4096    24.5         25.0
  8      4096    32.6         --
  =====  ======  ===========  =====

  so up to ``n_a = 6`` the default codebook keeps the binning error inside the push
  reward's cone (arccos 0.9 = 25.8 degrees); beyond that the codebook needs
  exponentially many directions and the default stays at 4096 (set ``bins``).
* ``"box"``: the grid ``{-c, 0, c}^n_a`` (``3^n_a`` codewords, up to ``n_a = 8``;
  ``bins`` unused): the
  corners, the faces' centres and "no move" on an axis; the corners alone could not
  hold one component still.  The nearest codeword rounds each component to the grid.

Loss ``E[(Q(s, g, k_a) - y)^2] + cql_alpha E[logsumexp_k Q(s, g, k) - Q(s, g, k_a)]``
with the Double DQN target ``y = r + gamma (1 - done) Q_t(s', g, argmax_k Q(s', g, k))``.
Squared error (as lazy Q's Eq. 10), not Huber: rewards are bounded, so the TD errors
are too and Huber's outlier robustness buys nothing.  Target network: Polyak
averaging (``tau`` 0.005), or a hard copy every ``target_period`` steps when
``target_period > 0``.  Policy: the codeword of the greedy ``k``.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax

from lazyq_jax.agents.base import Problem, Spec
from lazyq_jax.agents.common import (Baseline, BaselineConfig, apply_mlp, check, check_int,
                                     check_range, is_int, mask_of, mlp, observe, polyak, select,
                                     unit)
from lazyq_jax.types import Transitions

DEFAULT_DIRECTIONS = {1: 2, 2: 16, 3: 128, 4: 512, 5: 2048}
MAX_DIRECTIONS = 4096  # the default for n_a >= 6
MAX_BOX_CODES = 3 ** 8
COVERING_BOUND_DEG = {2: 11.3, 3: 14.5, 4: 20.5, 5: 21.5, 6: 25.0}  # see the docstring


@dataclasses.dataclass(frozen=True)
class DQNConfig(BaselineConfig):
    """:class:`BaselineConfig` plus ``bins`` (directions of the ball's codebook; None: by
    ``n_a``, 16 on the circle), ``cql_alpha`` (CQL(H) weight, 0 = plain Double DQN),
    ``tau`` (Polyak rate) and ``target_period`` (> 0: hard target copies every that
    many steps instead of Polyak averaging)."""

    bins: int | None = None
    cql_alpha: float = 0.0
    tau: float = 0.005
    target_period: int = 0

    def __post_init__(self) -> None:
        super().__post_init__()
        check(self.bins is None or (is_int(self.bins) and self.bins >= 2),
              f"DQNConfig.bins must be None (by n_a) or an integer >= 2, got {self.bins!r}")
        check_range(self, "cql_alpha", 0.0, math.inf)
        check_range(self, "tau", 0.0, 1.0, lo_open=True)
        check_int(self, "target_period", 0)


# ----------------------------------------------------------------------------- codebooks


def fibonacci_sphere(k: int) -> np.ndarray:
    """``k`` nearly uniform unit vectors of ``R^3`` (the Fibonacci lattice)."""
    i = np.arange(k) + 0.5
    z = 1.0 - 2.0 * i / k
    phi = np.pi * (1.0 + np.sqrt(5.0)) * i  # the golden angle times i
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def spherical_kmeans(n: int, k: int, iters: int = 20, per_codeword: int = 16,
                     seed: int = 0) -> np.ndarray:
    """``k`` unit vectors of ``R^n``: Lloyd's algorithm on the sphere (cells by the largest
    dot product, centres the normalised cell means) over ``per_codeword k`` uniform
    points of ``seed`` (deterministic)."""
    x = np.random.default_rng(seed).normal(size=(per_codeword * k, n)).astype(np.float32)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    centres = x[:k].copy()
    for _ in range(iters):
        cell = np.concatenate([np.argmax(chunk @ centres.T, axis=1)
                               for chunk in np.array_split(x, max(1, len(x) // 4096))])
        sums = np.stack([np.bincount(cell, weights=x[:, j], minlength=k) for j in range(n)], 1)
        norm = np.linalg.norm(sums, axis=1, keepdims=True)
        centres = np.where(norm > 0, sums / np.maximum(norm, 1e-12), centres).astype(np.float32)
    return centres


@functools.cache
def directions(n_a: int, k: int | None = None) -> np.ndarray:
    """The ball's codebook ``[K, n_a]`` of unit vectors (see the module docstring)."""
    if n_a == 1:
        return np.array([[1.0], [-1.0]], np.float32)
    k = (DEFAULT_DIRECTIONS.get(n_a, MAX_DIRECTIONS) if k is None else k)
    if n_a == 2:
        theta = 2 * np.pi * np.arange(k) / k
        out = np.stack([np.cos(theta), np.sin(theta)], axis=1)
    elif n_a == 3:
        out = fibonacci_sphere(k)
    else:
        out = spherical_kmeans(n_a, k)
    return out.astype(np.float32)


def codebook(problem: Problem, n_a: int, bins: int | None = None) -> np.ndarray:
    """The actions ``[K, n_a]`` DQN chooses among (see the module docstring)."""
    if problem.action_set == "box":
        if 3 ** n_a > MAX_BOX_CODES:
            raise ValueError(f"DQN's box codebook {{-c, 0, c}}^{n_a} would have 3^{n_a} "
                             f"codewords (at most {MAX_BOX_CODES}); use the ball or another "
                             "agent for this many action dimensions")
        grid = np.array(list(itertools.product((-1.0, 0.0, 1.0), repeat=n_a)), np.float32)
        return problem.action_length * grid
    return problem.action_length * directions(n_a, bins)


def nearest(problem: Problem, codes: jax.Array, a: jax.Array) -> jax.Array:
    """Index of the codeword nearest to each action ``a[..., n_a]``: by angle on the
    sphere (ball), by Euclidean distance in the box."""
    if problem.action_set == "ball":
        return jnp.argmax(unit(a) @ unit(codes).T, axis=-1)
    return jnp.argmax(a @ codes.T - 0.5 * jnp.sum(codes * codes, axis=-1), axis=-1)


# ----------------------------------------------------------------------------- the agent


class DQN(Baseline):
    name = "dqn"
    config_class = DQNConfig

    def __init__(self, config=None, problem=None, progress=None):
        super().__init__(config, problem, progress)
        self.optimizer = optax.adam(self.config.learning_rate)

    def init_model(self, key: jax.Array, spec: Spec) -> Any:
        codes = jnp.asarray(codebook(self.problem, spec.action_dim, self.config.bins))
        ex = spec.example()
        params = mlp(self.config, codes.shape[0]).init(key, observe(self.problem, ex.s, ex.g))
        return {"params": params, "target": params, "opt": self.optimizer.init(params),
                "codebook": codes}

    def q_all(self, params, s, g) -> jax.Array:
        return apply_mlp(self.config, params, observe(self.problem, s, g))  # [B, K]

    def loss(self, params, model, b: Transitions):
        cfg = self.config
        k_data = nearest(self.problem, model["codebook"], b.a)
        greedy = jnp.argmax(self.q_all(params, b.s_next, b.g), axis=-1)
        q_next = jnp.take_along_axis(self.q_all(model["target"], b.s_next, b.g),
                                     greedy[:, None], axis=-1)[:, 0]
        y = jax.lax.stop_gradient(b.r + cfg.gamma * mask_of(b) * q_next)
        q = self.q_all(params, b.s, b.g)
        q_data = jnp.take_along_axis(q, k_data[:, None], axis=-1)[:, 0]
        td = jnp.mean((q_data - y) ** 2)
        cql = jnp.mean(jax.nn.logsumexp(q, axis=-1) - q_data)
        return td + cfg.cql_alpha * cql, {"td_loss": td, "cql_gap": cql,
                                          "q_mean": jnp.mean(q_data)}

    def update(self, model, b, key, step):
        cfg = self.config
        grads, metrics = jax.grad(self.loss, has_aux=True)(model["params"], model, b)
        updates, opt = self.optimizer.update(grads, model["opt"], model["params"])
        params = optax.apply_updates(model["params"], updates)
        if cfg.target_period > 0:
            target = select((step + 1) % cfg.target_period == 0, params, model["target"])
        else:
            target = polyak(model["target"], params, cfg.tau)
        return {**model, "params": params, "target": target, "opt": opt}, metrics

    def actions(self, model, s, g):
        return model["codebook"][jnp.argmax(self.q_all(model["params"], s, g), axis=-1)]


def make(config: DQNConfig | None = None, problem: Problem | None = None,
         progress=None) -> DQN:
    """The DQN agent (``config`` None: the defaults)."""
    return DQN(config, problem, progress)
