"""The push task's data (paper §V-A-3): random pushes relabelled for many goals."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh

from lazyq_jax.data import episodes_to_transitions, run_episodes
from lazyq_jax.tasks.push.config import CollectConfig, PushConfig
from lazyq_jax.tasks.push.env import PushEnv
from lazyq_jax.tasks.push.reward import disk_moved, push_reward
from lazyq_jax.tasks.sampling import sample_outside_disk
from lazyq_jax.types import Transitions


def make_episode_fn(env: PushEnv, config: CollectConfig):
    """``episode(key) -> dict`` of one random episode, unbatched (vmap it).

    The finger starts uniform in ``[-R, R]^2`` outside the disk (at the origin) and
    makes ``moves_per_start`` moves in one uniformly random direction; each move is
    labelled with ``n_goals`` fresh goals uniform in ``[-pi, pi)``.
    """
    pc = env.config

    def episode(key):
        k_start, k_dir, k_goal = jax.random.split(key, 3)
        start = sample_outside_disk(k_start, jnp.zeros(2), config.start_range, pc.contact_distance)
        phi = jax.random.uniform(k_dir, (), jnp.float32, -jnp.pi, jnp.pi)
        action = pc.action_length * jnp.stack([jnp.cos(phi), jnp.sin(phi)])
        return repeated_moves(env.step, env.reset(start), action, k_goal, config, pc,
                              observe=lambda st: st.relative)

    return episode


def repeated_moves(step, state, action, key, config: CollectConfig, push: PushConfig, observe):
    """One §V-A-3 episode from ``state``: ``config.moves_per_start`` moves with ``action``
    (``step(state, action) -> (state, disk_delta)``), each labelled with
    ``config.n_goals`` goals uniform in ``[-pi, pi)`` and Eq. (15)'s rewards;
    ``observe(state)`` is the agent's state ``s``.  Returns the episode's dict (leaves
    ``[T, ...]``) for :func:`episodes_to_transitions`."""
    goals = jax.random.uniform(key, (config.moves_per_start, config.n_goals), jnp.float32,
                               -jnp.pi, jnp.pi)

    def move(state, _):
        nxt, delta = step(state, action)
        return nxt, (observe(state), observe(nxt), delta)

    _, (s, s_next, delta) = jax.lax.scan(move, state, None, length=config.moves_per_start)
    reward = push_reward(delta[:, None, :], goals, move_threshold=push.move_threshold,
                         cos_threshold=push.cos_threshold)
    return {"s": s, "a": jnp.broadcast_to(action, s.shape[:1] + action.shape), "s_next": s_next,
            "delta": delta,
            "g": goals, "r": reward, "moved": disk_moved(delta, push.move_threshold)}


def collect(key: jax.Array, config: CollectConfig = CollectConfig(), *, mesh: Mesh | None = None,
            progress: bool = True) -> Transitions:
    """Simulate the random pushes of §V-A-3 in jitted MJX batches and relabel for many goals.

    Returns ``Transitions`` with ``n_goals`` rows per simulated move, push-major
    (row ``= move * n_goals + goal``).  ``s`` is the finger position relative to the disk.

    Episodes end at a push that moves the disk (``|delta| >= move_threshold``, which
    gives reward +-1 for every goal): that push is a terminal transition
    (``done=True``), and the episode's later moves are never part of the dataset
    (the paper resets the disk).  So ``N <= n_starts * moves_per_start * n_goals``;
    with the paper's 5000 x 2 x 100 that is at most 1,000,000 rows.

    ``mesh`` (see :mod:`lazyq_jax.parallel`): the chunks of ``chunk_size`` episodes are
    spread over its devices with ``shard_map``, one chunk per device and call; with
    several processes each simulates the chunks of its own devices and all receive
    the whole dataset.

    Same ``key`` and config give the bitwise same dataset on any number of devices:
    every device runs the same program on a chunk of the same size, which holds the
    same episodes.  (Another ``chunk_size`` can change the last bits of a few
    episodes: XLA's vectorised code depends on the batch size.)  The physics runs in
    float64 when ``config.push.float64`` (see :class:`PushConfig`).
    """
    if not isinstance(config, CollectConfig):
        raise TypeError(f"collect needs a CollectConfig, got {type(config).__name__}")
    make = lambda: make_episode_fn(PushEnv(config.push), config)
    eps = run_episodes(key, make, config, config.n_starts, config.chunk_size,
                       float64=config.push.float64, mesh=mesh, progress=progress)
    return episodes_to_transitions(eps, config.n_goals)


def dataset_summary(data: Transitions, n_goals: int) -> dict:
    """Counts the README reports: moves, moves that moved the disk, rewards per goal octant.

    Octant ``i`` holds the goals within 22.5 degrees of ``45 * i`` degrees: octants
    0, 2, 4, 6 are centred on the axes (0, 90, 180, 270), the others on diagonals.
    """
    r = np.asarray(data.r)
    octant = np.round(np.asarray(data.g) / (np.pi / 4)).astype(int) % 8
    per = []
    for i in range(8):
        m = octant == i
        per.append({"centre_deg": 45 * i, "positive": int(np.sum(r[m] > 0)),
                    "negative": int(np.sum(r[m] < 0)), "zero": int(np.sum(r[m] == 0))})
    return {"rows": int(r.size), "moves": int(r.size // n_goals),
            "moves_that_moved_disk": int(np.asarray(data.done).sum() // n_goals),
            "reward_by_goal_octant": per}
