"""Shared fixtures: one PushEnv and one compiled batched push for the whole session.

MJX compiles take seconds on CPU, so tests pad their pushes to a fixed batch.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lazyq_jax.config import PushConfig
from lazyq_jax.env import PushEnv

PUSH_BATCH = 16


@pytest.fixture(scope="session")
def env() -> PushEnv:
    return PushEnv(PushConfig())


@pytest.fixture(scope="session")
def push(env):
    """``push(finger[B,2], action[B,2], disk[B,2]=0) -> (finger_after, disk_delta)`` as NumPy."""
    step = jax.jit(jax.vmap(env.step))

    def run(finger, action, disk=None):
        finger = np.asarray(finger, np.float32).reshape(-1, 2)
        action = np.asarray(action, np.float32).reshape(-1, 2)
        disk = np.zeros_like(finger) if disk is None else np.asarray(disk, np.float32).reshape(-1, 2)
        n = finger.shape[0]
        assert n <= PUSH_BATCH
        pad = lambda x, fill: np.concatenate([x, np.tile(fill, (PUSH_BATCH - n, 1))]).astype(np.float32)
        state = env.reset(pad(finger, [0.9, 0.9]), pad(disk, [0.0, 0.0]))
        nxt, delta = step(state, jnp.asarray(pad(action, [1.0, 0.0])))
        return np.asarray(nxt.finger_xy)[:n], np.asarray(delta)[:n]

    return run
