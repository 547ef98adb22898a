"""How precisely must a push aim for a diagonal goal in the paper world?

Head-on pushes (the finger 0.33 from the disk centre, moving through it) at angles
just below 45 degrees, in float64 MJX: the direction in which the disk moves and
whether that is "correct" for the 45-degree goal (cos >= 0.9, §V-B).  The window of
correct push directions bounds what any policy (learned online or not) can achieve
for diagonal goals with the paper's actions.

    .venv/bin/python experiments/diagonal_window.py [--mu 2.0]
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import numpy as np

from lazyq_jax.tasks.push import PushConfig, PushEnv


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--mu", type=float, default=2.0, help="Coulomb friction coefficient (paper preset: 2)")
    args = ap.parse_args()
    deg = np.array([45.0, 44.9, 44.75, 44.5, 44.25, 44.0, 43.0, 40.0])
    a = np.radians(deg)
    d = np.stack([np.cos(a), np.sin(a)], 1)
    with jax.enable_x64(True):
        env = PushEnv(PushConfig(friction_coefficient=args.mu))
        step = jax.jit(jax.vmap(env.step))
        state = env.reset(jnp.asarray(-0.33 * d, jnp.float32))
        moves = []
        for _ in range(3):  # the finger reaches the disk within three moves
            state, delta = step(state, jnp.asarray(d, jnp.float32))
            moves.append(np.asarray(delta))
    print(f"Coulomb mu = {args.mu}: head-on pushes toward the 45-degree goal")
    for j, x in enumerate(deg):
        first = next(m[j] for m in moves if np.linalg.norm(m[j]) >= env.config.move_threshold)
        ang = np.degrees(np.arctan2(first[1], first[0]))
        ok = np.cos(np.radians(ang - 45.0)) >= env.config.cos_threshold
        print(f"push at {x:6.2f} deg -> disk moves at {ang:6.2f} deg: {'correct' if ok else 'wrong'}")


if __name__ == "__main__":
    main()
