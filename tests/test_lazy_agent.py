"""The lazy agent's policies over several seeds whose search space is the paper's (states
[N, 2] with angle goals) without bounds from the task (e.g. a 2-D feature map)."""

import jax
import jax.numpy as jnp
import numpy as np

from lazyq_jax.agents import lazy
from lazyq_jax.agents.base import Problem, stack_trees
from lazyq_jax.agents.reference import line_task
from lazyq_jax.config import NeighbourConfig, TrainConfig
from lazyq_jax.parallel import over_seeds
from lazyq_jax.types import pad_transitions


def test_seeds_grids_share_bounds_when_the_task_gives_none():
    """Two seeds with different data (so different extents): the policies stack into one
    pytree (one layout, covering both) and act (moves of length c; none where
    no neighbourhood is found)."""
    data = [line_task(0, 2000, d=2, goal="angle"), line_task(1, 1500, d=2, goal="angle")]
    data[1] = data[1].replace(s=data[1].s * 0.8, s_next=data[1].s_next * 0.8)  # a smaller extent
    n = max(d.size for d in data)
    stacked = stack_trees([pad_transitions(d, n) for d in data])
    n_valid = np.array([d.size for d in data], np.int32)
    agent = lazy.make(lazy.LazyConfig(train=TrainConfig(cycles=1, width=8, depth=2),
                                      neighbours=NeighbourConfig(k=10, radius_s=0.1, radius_g=0.3)),
                      Problem(action_length=0.1))
    assert agent.problem.search_bounds is None
    states = over_seeds(agent.init, 2)(jnp.stack([jax.random.PRNGKey(0), jax.random.PRNGKey(1)]), stacked)
    policy = agent.policies(states, stacked, n_valid)
    s = jnp.asarray(np.random.default_rng(0).uniform(-0.7, 0.7, (2, 16, 2)), jnp.float32)
    g = jnp.asarray(np.random.default_rng(1).uniform(-np.pi, np.pi, (2, 16)), jnp.float32)
    keys = jnp.stack([jax.random.PRNGKey(2), jax.random.PRNGKey(3)])
    actions = jax.vmap(lambda p, k, s_, g_: agent.act(p)(k, s_, g_))(policy, keys, s, g)
    assert actions.shape == (2, 16, 2) and bool(jnp.all(jnp.isfinite(actions)))
    norms = np.linalg.norm(np.asarray(actions), axis=-1)
    assert np.all((np.abs(norms - 0.1) < 1e-5) | (norms == 0)) and np.mean(norms > 0) > 0.9
