"""Pytree containers shared across the pipeline."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct


@struct.dataclass
class Transitions:
    """A batch of goal-relabelled transitions ``d = (s, a, s', r, g, done)`` (paper §III).

    All leaves share the leading dimension ``N``:

    * ``s, s_next``: float32 ``[N, d_s]``: state and next state (for the push task
      ``d_s = 2``, the finger position relative to the disk).
    * ``a``: float32 ``[N, n_a]``: the action (a finger move, a joint move, ...).
    * ``r``: float32 ``[N]``: the reward ``R(s, a, g)`` (Eq. 15 for the push task).
    * ``g``: the goal: float32 ``[N]`` an angle in ``[-pi, pi)`` (periodic), float32
      ``[N, d_g]`` a vector (Euclidean), or ``None`` (no goal).
    * ``done``: bool ``[N]``: terminal transition (not bootstrapped).
    * ``traj_last``: optional int32 ``[N]``: when the rows are trajectories (a trajectory's
      transitions in consecutive rows), the row of the last transition of each row's
      trajectory.  Goal-conditioned agents (OGBench's) then draw fresh goals from the
      trajectories every minibatch; ``None`` (default) for data that are not trajectories.

    Nothing here is specific to a task: any ``Transitions`` works with the lazy core
    and the training code.
    """

    s: jax.Array
    a: jax.Array
    s_next: jax.Array
    r: jax.Array
    g: jax.Array | None
    done: jax.Array
    traj_last: jax.Array | None = None

    @property
    def size(self) -> int:
        return int(self.r.shape[0])

    def astype_canonical(self) -> "Transitions":
        """The canonical dtypes (float32 arrays, bool ``done``)."""
        f = lambda x: jnp.asarray(x, jnp.float32)
        return Transitions(
            s=f(self.s), a=f(self.a), s_next=f(self.s_next), r=f(self.r),
            g=None if self.g is None else f(self.g),
            done=jnp.asarray(self.done, bool),
            traj_last=None if self.traj_last is None else jnp.asarray(self.traj_last, jnp.int32),
        )


def pad_transitions(data: Transitions, n: int) -> Transitions:
    """``data`` with zero rows appended up to ``n`` rows (``done`` False).

    Used to stack datasets of different sizes (one per seed) for ``jax.vmap``; pass
    each dataset's true size as ``n_valid`` to the training functions, which then
    ignore the padding (see :mod:`lazyq_jax.train`).
    """
    size = data.size
    if n < size:
        raise ValueError(f"cannot pad {size} rows to {n}")
    return jax.tree.map(lambda x: jnp.concatenate([x, jnp.zeros((n - size, *x.shape[1:]), x.dtype)]),
                        data)
