"""The agent registry: lazy Q and every baseline, one file each, one line each below.

>>> agent = lazyq_jax.agents.make("iql", None, action_length=0.1)   # default IQLConfig
>>> state, metrics = jax.jit(agent.train)(key, data)              # sizes from the data
>>> actions = agent.policy(state)(key, s, g)                      # [B, n_a]

Every agent takes its sizes (``d_s``, ``n_a``, the goal kind) from the data and its
task from a :class:`~lazyq_jax.agents.base.Problem` (the action set and input scales);
see :mod:`lazyq_jax.agents.base` for the interface.  A new agent is one file with a
config dataclass and ``make(config, problem, ...)``, and one line in :data:`AGENTS`
(docs/design.md, "Adding an agent").  ``scripted`` is each task's own controller (made
by the runner from the task); ``random`` the chance level.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from lazyq_jax.agents import bc, crl, dqn, gcbc, gciql, gcivl, hiql, iql, lazy, naf, qrl, reference, td3bc
from lazyq_jax.agents.base import Act, Agent, FixedPolicy, Problem, Spec
from lazyq_jax.agents.bc import BCConfig
from lazyq_jax.agents.crl import CRLConfig
from lazyq_jax.agents.common import BaselineConfig
from lazyq_jax.agents.dqn import DQNConfig
from lazyq_jax.agents.gcbc import GCBCConfig
from lazyq_jax.agents.gciql import GCIQLConfig
from lazyq_jax.agents.gcivl import GCIVLConfig
from lazyq_jax.agents.hiql import HIQLConfig
from lazyq_jax.agents.iql import IQLConfig
from lazyq_jax.agents.lazy import LazyAgent, LazyConfig
from lazyq_jax.agents.naf import NAFConfig
from lazyq_jax.agents.qrl import QRLConfig
from lazyq_jax.agents.td3bc import TD3BCConfig
from lazyq_jax.config import ConfigError

# name -> (config class or None, make(config, problem) -> Agent)
AGENTS: dict[str, tuple[type | None, Callable[..., Agent]]] = {
    "lazy": (LazyConfig, lazy.make),
    "iql": (IQLConfig, iql.make),
    "td3bc": (TD3BCConfig, td3bc.make),
    "dqn": (DQNConfig, dqn.make),
    "naf": (NAFConfig, naf.make),
    "bc": (BCConfig, bc.make),
    "gcivl": (GCIVLConfig, gcivl.make),
    "gciql": (GCIQLConfig, gciql.make),
    "gcbc": (GCBCConfig, gcbc.make),
    "qrl": (QRLConfig, qrl.make),
    "crl": (CRLConfig, crl.make),
    "hiql": (HIQLConfig, hiql.make),
    "random": (None, reference.make),
}
BASELINES = ("iql", "td3bc", "dqn", "naf", "bc", "gcivl", "gciql", "gcbc", "qrl", "crl", "hiql")
METHODS = (*AGENTS, "scripted")


def config_class(name: str) -> type | None:
    """The config dataclass of agent ``name`` (None for agents without settings)."""
    return _entry(name)[0]


def _entry(name: str):
    if name == "scripted":
        raise ConfigError("'scripted' is a task's own controller: run it with --methods scripted "
                          "(the runner asks the task), or call task.scripted(config)")
    if name not in AGENTS:
        raise ConfigError(f"unknown method {name!r}; known methods: {', '.join(METHODS)}")
    return AGENTS[name]


def make(name: str, config: Any = None, action_length: float = 0.1, *, problem: Problem | None = None,
         **options) -> Agent:
    """Agent ``name`` with ``config`` (None: its defaults) for actions of length
    ``action_length`` on the ball (or a whole ``problem``: action set, input scales, ...).

    ``options``: lazy Q takes ``mesh``, the baselines ``progress``.  Raises
    ``ConfigError`` for an unknown name (listing the known ones) and ``TypeError`` for a
    config of another agent's class.
    """
    cls, build = _entry(name)
    problem = Problem(action_length=action_length) if problem is None else problem
    if cls is not None and config is not None and type(config) is not cls:
        raise TypeError(f"agent {name!r} needs a {cls.__name__} (or None), got {type(config).__name__}")
    return build(config, problem, **options)


__all__ = [
    "AGENTS",
    "BASELINES",
    "METHODS",
    "Act",
    "Agent",
    "BCConfig",
    "CRLConfig",
    "BaselineConfig",
    "DQNConfig",
    "FixedPolicy",
    "GCBCConfig",
    "GCIQLConfig",
    "GCIVLConfig",
    "HIQLConfig",
    "IQLConfig",
    "LazyAgent",
    "LazyConfig",
    "NAFConfig",
    "Problem",
    "QRLConfig",
    "Spec",
    "TD3BCConfig",
    "config_class",
    "make",
]
