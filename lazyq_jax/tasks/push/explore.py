"""The push task's online rounds: the agent gathers its own pushes (beyond the paper).

One round of one seed is :func:`explore_round`: ``online.episodes`` episodes in one
``lax.scan`` of ``online.max_steps`` moves, each move the agent's (Eq. 9 for lazy Q)
with exploration, every move relabelled for ``collect.n_goals`` goals (Eq. 15,
§V-A-3).  Pure: the runner ``vmap``s it over seeds.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from lazyq_jax.agents.base import Act
from lazyq_jax.config import Config
from lazyq_jax.tasks.push.env import PushEnv
from lazyq_jax.tasks.push.reward import disk_moved, push_reward
from lazyq_jax.tasks.sampling import sample_outside_disk


def explore_round(act: Act, key: jax.Array, config: Config) -> dict:
    """Episodes of ``act`` with exploration (see :class:`lazyq_jax.config.OnlineConfig`):
    goal uniform in ``[-pi, pi)``, the disk at the origin, the finger within
    ``collect.explore_range`` of it (behind it for ``explore_start = "behind"``); per
    move a uniformly random direction with probability ``epsilon`` or where the agent
    gives no move (lazy Q without a neighbourhood), else the agent's direction turned
    by ``N(0, action_noise^2)`` radians.  An episode ends at the first move that moves
    the disk; its later moves are recorded as zero displacements and dropped by
    :func:`~lazyq_jax.data.episodes_to_transitions`.

    Returns leaves ``[episodes, max_steps, ...]`` (``s, a, s_next, moved``; ``g, r``:
    the ``n_goals`` relabelled goals of each move and their Eq. (15) rewards) and
    ``counts``: episodes, pushed (the disk moved), correct (pushed toward the
    episode's goal, protocol A's test), and the same for the diagonal goals.
    """
    push, o, c = config.collect.push, config.online, config.collect
    env = PushEnv(push)
    b, length = o.episodes, push.action_length

    def start(key, g):
        behind = None if c.explore_start == "anywhere" else (
            lambda x: x @ jnp.stack([jnp.cos(g), jnp.sin(g)]) < 0)
        return sample_outside_disk(key, jnp.zeros(2), c.explore_range, push.contact_distance, behind)

    k_goal, k_start, k_run, k_label = jax.random.split(key, 4)
    goals = jax.random.uniform(k_goal, (b,), jnp.float32, -jnp.pi, jnp.pi)
    finger = jax.vmap(start)(jax.random.split(k_start, b), goals)
    step = jax.vmap(env.step)

    def move(carry, k):
        state, done = carry
        k_pol, k_eps, k_dir, k_noise = jax.random.split(k, 4)
        s = state.relative
        greedy = act(k_pol, s, goals)
        found = jnp.any(greedy != 0, axis=-1)
        phi = jnp.arctan2(greedy[:, 1], greedy[:, 0])
        phi = phi + o.action_noise * jax.random.normal(k_noise, (b,))
        explore = (jax.random.uniform(k_eps, (b,)) < o.epsilon) | ~found
        phi = jnp.where(explore, jax.random.uniform(k_dir, (b,), jnp.float32, -jnp.pi, jnp.pi), phi)
        action = length * jnp.stack([jnp.cos(phi), jnp.sin(phi)], -1)
        new, delta = step(state, action)
        live = ~done
        delta = jnp.where(live[:, None], delta, 0.0)
        moved = disk_moved(delta, push.move_threshold)
        state = jax.tree.map(lambda n, old: jnp.where(live[:, None], n, old), new, state)
        return (state, done | moved), (s, action, state.relative, delta, moved)

    init = (env.reset(finger, jnp.zeros_like(finger)), jnp.zeros(b, bool))
    _, out = jax.lax.scan(move, init, jax.random.split(k_run, o.max_steps))
    s, a, s_next, delta, moved = (jnp.swapaxes(x, 0, 1) for x in out)  # [B, T, ...]
    labels = jax.random.uniform(k_label, (b, o.max_steps, c.n_goals), jnp.float32, -jnp.pi, jnp.pi)
    reward = push_reward(delta[:, :, None, :], labels, move_threshold=push.move_threshold,
                         cos_threshold=push.cos_threshold)
    return {"s": s, "a": a, "s_next": s_next, "moved": moved, "g": labels, "r": reward,
            "goal": goals, "counts": episode_counts(delta, moved, goals, push.cos_threshold)}


def episode_counts(delta, moved, goals, cos_threshold):
    """Counts of a round's episodes (``delta [B, T, 2]`` disk displacements, ``moved [B,
    T]``, ``goals [B]``): pushed, pushed toward the goal (``cos >= cos_threshold``, protocol
    A's test), and the same for the diagonal goals."""
    pushed = moved.any(axis=1)
    first = jnp.argmax(moved, axis=1)
    d = jnp.take_along_axis(delta, first[:, None, None], axis=1)[:, 0]  # [B, 2]
    cos = ((d[:, 0] * jnp.cos(goals) + d[:, 1] * jnp.sin(goals))
           / jnp.maximum(jnp.linalg.norm(d, axis=1), 1e-12))
    correct = pushed & (cos >= cos_threshold)
    diagonal = jnp.mod(jnp.round(goals / (jnp.pi / 4)), 2) != 0
    count = lambda m: jnp.sum(m, dtype=jnp.int32)
    return {"episodes": jnp.int32(goals.shape[0]), "pushed": count(pushed), "correct": count(correct),
            "diagonal_episodes": count(diagonal), "diagonal_correct": count(correct & diagonal)}
