"""Offline RL baselines trained on the same static dataset as lazy Q.

>>> import lazyq_jax.baselines as bl
>>> agent = bl.make("iql", config=None, action_length=0.1)   # default IQLConfig
>>> state, metrics = jax.jit(agent.train)(key, data)          # optional n_valid=...
>>> actions = agent.policy(state)(key, s, g)                  # [B, 2], |a| = 0.1

``train(key, data, n_valid=None)`` is pure (one ``lax.scan`` of ``config.steps``
updates; randomness only from ``key``): ``jax.vmap`` it over keys, and over datasets
stacked by padding (:func:`lazyq_jax.types.pad_transitions`) with each one's
``n_valid``; rows ``>= n_valid`` are never sampled.  ``metrics`` holds per-block
means (``[max(1, steps // log_every)]``).  Policies are deterministic (the key is
unused) and return ``c u / |u|``, never NaN.

Methods (one module each, citing its paper): ``iql`` (implicit Q-learning, von Mises
AWR actor), ``td3bc`` (TD3+BC), ``dqn`` (Double DQN over direction bins, optional
CQL), ``naf`` (normalized advantage functions with the maximiser on the circle),
``bc`` (behaviour cloning of the r = +1 rows).  :func:`random_policy` is the chance
level; the scripted push controller (an upper bound that learns nothing) lives with
its task in :mod:`lazyq_jax.env.scripted`.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import jax
import jax.numpy as jnp

from lazyq_jax.baselines import bc, dqn, iql, naf, td3bc
from lazyq_jax.baselines.bc import BCConfig
from lazyq_jax.baselines.common import Act, Agent, BaselineConfig, check_action_length
from lazyq_jax.baselines.dqn import DQNConfig
from lazyq_jax.baselines.iql import IQLConfig
from lazyq_jax.baselines.naf import NAFConfig
from lazyq_jax.baselines.td3bc import TD3BCConfig
from lazyq_jax.config import ConfigError

_REGISTRY = {
    "iql": (IQLConfig, iql.make),
    "td3bc": (TD3BCConfig, td3bc.make),
    "dqn": (DQNConfig, dqn.make),
    "naf": (NAFConfig, naf.make),
    "bc": (BCConfig, bc.make),
}
METHODS: tuple[str, ...] = tuple(_REGISTRY)


def _entry(name: str):
    if name not in _REGISTRY:
        raise ConfigError(f"unknown baseline {name!r}; known: {', '.join(METHODS)}")
    return _REGISTRY[name]


def config_class(name: str) -> type:
    """The config dataclass of method ``name`` (``ConfigError`` if unknown)."""
    return _entry(name)[0]


def make(name: str, config: BaselineConfig | None = None, action_length: float = 0.1, *,
         progress: Callable[[int], None] | None = None) -> Agent:
    """The :class:`Agent` of method ``name`` with ``config`` (None: the defaults).

    ``progress``, if given, is called on the host with the step number every
    ``config.log_every`` steps of ``train`` (``jax.debug.callback``; once per seed
    under ``vmap``), e.g. to drive a progress bar.  Raises ``ConfigError`` for an
    unknown name or a bad ``action_length``, and ``TypeError`` for a config of
    another method's (or no config) class.
    """
    cls, build = _entry(name)
    if config is None:
        config = cls()
    if not (dataclasses.is_dataclass(config) and type(config) is cls):
        raise TypeError(f"baseline {name!r} needs a {cls.__name__} (or None), "
                        f"got {type(config).__name__}")
    return build(config, check_action_length(action_length), progress)


def random_policy(action_length: float = 0.1) -> Act:
    """``act(key, s[B, 2], g[B]) -> actions[B, 2]``: uniformly random directions of length
    ``action_length`` (chance level; the key matters)."""
    c = check_action_length(action_length)

    def act(key, s, g):
        theta = jax.random.uniform(key, (s.shape[0],), minval=-jnp.pi, maxval=jnp.pi)
        return c * jnp.stack([jnp.cos(theta), jnp.sin(theta)], axis=-1)

    return act


__all__ = ["METHODS", "Act", "Agent", "BCConfig", "BaselineConfig", "DQNConfig", "IQLConfig",
           "NAFConfig", "TD3BCConfig", "config_class", "make", "random_policy"]
