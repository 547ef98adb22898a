"""A scripted push controller: an upper bound that knows the physics and learns nothing.

``s`` is the finger relative to the disk centre, ``g`` the goal angle, ``u = (cos g, sin g)``.
Each step is one move of length ``c`` (the env rescales any action to ``c``):

1. **Behind** (the finger within ``angle_tolerance`` of the ray ``-u``, at any
   distance): move straight toward the centre.  The finger walks down the ray and
   pushes through the centre, so the disk moves along the contact normal, within
   ``angle_tolerance`` of ``u`` (15 degrees: cos 0.966, inside Eq. 15's 0.9; in the
   Coulomb world the per-axis friction pulls an axis push further onto the axis).
2. **Clear way** to the waypoint ``p = -(contact + margin) u`` just behind the disk
   (neither the whole segment to ``p`` nor this step comes within
   ``contact + margin / 2`` of the centre): move straight toward ``p``.
3. **Detour** otherwise: move along the tangent from the finger to the circle of
   radius ``contact + 1.5 margin``, turning the short way round toward ``-u``; such a
   line never comes closer to the centre than that radius (inside it the move is
   purely tangential and only moves outward).

The disk is never touched except by the push of case 1.  Diagonal goals in the
paper's Coulomb world are another matter: a head-on diagonal push is deflected
toward an axis (see :class:`lazyq_jax.config.PushConfig`), and this controller does
not compensate for it.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from lazyq_jax.tasks.push.config import PushConfig


def _unit(v: jax.Array) -> jax.Array:
    n = jnp.linalg.norm(v, axis=-1, keepdims=True)
    fallback = jnp.zeros_like(v).at[..., 0].set(1.0)
    return jnp.where(n > 0, v / jnp.where(n > 0, n, 1.0), fallback)


def _segment_distance(a: jax.Array, b: jax.Array) -> jax.Array:
    """Distance of the origin to the segments ``a[B, 2] -> b[B, 2]``."""
    d = b - a
    t = jnp.clip(-jnp.sum(a * d, -1) / jnp.maximum(jnp.sum(d * d, -1), 1e-12), 0.0, 1.0)
    return jnp.linalg.norm(a + t[:, None] * d, axis=-1)


def _rotate(v: jax.Array, angle: jax.Array) -> jax.Array:
    cos, sin = jnp.cos(angle), jnp.sin(angle)
    return jnp.stack([cos * v[:, 0] - sin * v[:, 1], sin * v[:, 0] + cos * v[:, 1]], -1)


def scripted_push_policy(config: PushConfig = PushConfig(), *, margin: float = 0.02,
                         angle_tolerance: float = math.radians(15.0)):
    """``act(key, s[B, 2], g[B]) -> actions[B, 2]`` of length ``action_length`` (see module
    docstring; the key is unused).  Pure ``jnp``; jit and vmap freely."""
    if not margin > 0 or not 0 < angle_tolerance < math.pi / 2:
        raise ValueError(f"need margin > 0 and 0 < angle_tolerance < pi / 2, got {margin}, "
                         f"{angle_tolerance}")
    c = config.action_length
    contact = config.contact_distance
    behind_r, clear_r, orbit_r = contact + margin, contact + margin / 2, contact + 1.5 * margin
    cos_tol = math.cos(angle_tolerance)

    def act(key, s, g):
        s = jnp.asarray(s, jnp.float32)
        g = jnp.asarray(g, jnp.float32)
        u = jnp.stack([jnp.cos(g), jnp.sin(g)], -1)
        r = jnp.linalg.norm(s, axis=-1)
        s_hat = _unit(s)

        behind = jnp.sum(s_hat * -u, -1) >= cos_tol

        waypoint = -behind_r * u
        to_waypoint = _unit(waypoint - s)
        clear = ((_segment_distance(s, waypoint) >= clear_r)
                 & (_segment_distance(s, s + c * to_waypoint) >= clear_r))

        # Turn toward -u the short way: +1 counter-clockwise (-u lies counter-clockwise of s).
        cross = s[:, 0] * -u[:, 1] - s[:, 1] * -u[:, 0]
        sigma = jnp.where(cross >= 0, 1.0, -1.0)
        beta = jnp.arcsin(jnp.clip(orbit_r / jnp.maximum(r, 1e-6), 0.0, 1.0))
        detour = _rotate(-s_hat, -sigma * beta)

        direction = jnp.where(behind[:, None], -s_hat,
                              jnp.where(clear[:, None], to_waypoint, detour))
        return c * direction

    return act
