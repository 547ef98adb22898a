"""The push task's reward, Eq. (15)."""

from __future__ import annotations

import jax
import jax.numpy as jnp


def push_reward(disk_delta: jax.Array, goal_angle: jax.Array, *, move_threshold: float = 0.01,
                cos_threshold: float = 0.9) -> jax.Array:
    """Eq. (15): 0 if the disk did not move, +1 if it moved in the goal direction, else -1.

    Args:
      disk_delta: ``[..., 2]`` displacement of the disk during one push.
      goal_angle: ``[...]`` goal direction, an angle (broadcasts against ``disk_delta[..., 0]``).
      move_threshold: the disk counts as moved when ``|delta| >= move_threshold``.
      cos_threshold: the direction is correct when ``cos(angle(delta, g)) > cos_threshold``
        (strictly, as in §V-A-1).

    Returns:
      float32 rewards in ``{-1, 0, 1}`` of the broadcast shape.  A push that moved the
      disk has a nonzero reward for every goal, so ``reward != 0`` marks terminal steps.
    """
    delta = jnp.asarray(disk_delta, jnp.float32)
    goal = jnp.asarray(goal_angle, jnp.float32)
    dist = jnp.linalg.norm(delta, axis=-1)
    moved = dist >= move_threshold
    direction = jnp.stack([jnp.cos(goal), jnp.sin(goal)], axis=-1)
    cos = jnp.sum(delta * direction, axis=-1) / jnp.where(moved, dist, 1.0)
    return jnp.where(moved, jnp.where(cos > cos_threshold, 1.0, -1.0), 0.0).astype(jnp.float32)


def disk_moved(disk_delta: jax.Array, move_threshold: float = 0.01) -> jax.Array:
    """Whether a push moved the disk (``|delta| >= move_threshold``): the episode ends."""
    return jnp.linalg.norm(jnp.asarray(disk_delta, jnp.float32), axis=-1) >= move_threshold
