"""The same pushes in native MuJoCo (``mujoco.rollout``), for cross-checks and benchmarks."""

from __future__ import annotations

import copy

import mujoco
import numpy as np
from mujoco import rollout

from lazyq_jax.tasks.push.env import PushEnv, coulomb_friction, normalize_action


def native_push(env: PushEnv, finger_xy: np.ndarray, disk_xy: np.ndarray, action: np.ndarray,
                nthread: int = 1, datas: list | None = None) -> np.ndarray:
    """Final disk positions ``[B, 2]`` of a batch of pushes simulated by native MuJoCo.

    Same model (``env.mj_model``), same finger path as :meth:`PushEnv.step`.  Runs
    in float64 on ``nthread`` threads; pass ``datas`` (``nthread`` ``MjData``) to
    reuse them across calls.  The ``"coulomb"`` friction is set from Python before
    every substep, one push after another (:func:`_native_coulomb_push`): a
    reference, not a fast path (``nthread`` and ``datas`` are not used for it).
    """
    model, cfg = env.mj_model, env.config
    finger = np.asarray(finger_xy, np.float64).reshape(-1, 2)
    disk = np.asarray(disk_xy, np.float64).reshape(-1, 2)
    act = np.asarray(normalize_action(np.asarray(action, np.float32), cfg.action_length),
                     np.float64).reshape(-1, 2)
    batch = finger.shape[0]
    frac = np.minimum(np.arange(1, cfg.substeps + 1) / cfg.move_substeps, 1.0)
    path = finger[:, None, :] + frac[None, :, None] * act[:, None, :]
    if cfg.friction == "coulomb":
        return np.stack([_native_coulomb_push(env, p, d) for p, d in zip(path, disk)])
    control = np.concatenate([path, np.zeros((batch, cfg.substeps, 1))], axis=-1)

    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    data = mujoco.MjData(model)
    state0 = np.empty(mujoco.mj_stateSize(model, spec))
    mujoco.mj_getState(model, data, state0, spec)
    qpos_at = 1  # FULLPHYSICS = [time, qpos, qvel, ...]
    init = np.tile(state0, (batch, 1))
    init[:, qpos_at:qpos_at + 2] = disk
    if datas is None:
        datas = [mujoco.MjData(model) for _ in range(nthread)]
    states, _ = rollout.rollout(model, datas, init, control,
                                control_spec=mujoco.mjtState.mjSTATE_MOCAP_POS)
    return states[:, -1, qpos_at:qpos_at + 2]


def _native_coulomb_push(env: PushEnv, path: np.ndarray, disk_xy: np.ndarray) -> np.ndarray:
    """One push with the ``"coulomb"`` friction linearised before every ``mj_step``, as in MJX."""
    model = copy.copy(env.mj_model)
    data = mujoco.MjData(model)
    data.qpos[:2] = disk_xy
    for finger_xy in path:
        data.mocap_pos[0] = (*finger_xy, 0.0)
        damping, force = coulomb_friction(data.qvel[:2].copy(), env.config)
        model.dof_damping[:2] = damping
        data.qfrc_applied[:2] = force
        mujoco.mj_step(model, data)
    return data.qpos[:2].copy()
