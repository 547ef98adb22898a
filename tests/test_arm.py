"""The arm-pushes-disk scene: kinematics, limits, starts, contact, MJX vs native MuJoCo.

One float64 ArmEnv and one compiled batched step (:data:`BATCH` pushes) serve the file.
"""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from lazyq_jax.config import ConfigError
from lazyq_jax.tasks.arm.env import (
    ArmConfig,
    ArmEnv,
    ArmState,
    arm_reward,
    fingertip_xy,
    joint_path,
    native_arm_push,
    sample_arm_start,
)
from lazyq_jax.tasks.arm.config import ArmCollectConfig, ArmEvalConfig
from lazyq_jax.tasks.arm.episodes import protocol_a
from lazyq_jax.tasks.base import CORRECT, NOT_PUSHED, WRONG, run_protocol, seed_acts
from lazyq_jax.tasks.push import PushConfig
from lazyq_jax.tasks.push.env import load_mj_model, normalize_action
from lazyq_jax.tasks.push.protocols import summarize_a

BATCH = 16
CFG = ArmConfig()
LO, HI = np.array(CFG.joint_lower), np.array(CFG.joint_upper)


@pytest.fixture(scope="module")
def arm():
    with jax.enable_x64(True):
        env = ArmEnv(CFG)
        step = jax.jit(jax.vmap(env.step))
    assert env.dtype == jnp.float64

    def push(q, dq, disk=None):
        """``(q_after, disk_delta)`` of pushes ``[n <= BATCH]``, padded to one compiled batch."""
        q = np.asarray(q, np.float32).reshape(-1, 3)
        dq = np.asarray(dq, np.float32).reshape(-1, 3)
        disk = np.zeros((len(q), 2), np.float32) if disk is None else np.asarray(disk, np.float32)
        n = len(q)
        pad = lambda x, fill: np.concatenate([x, np.tile(fill, (BATCH - n, 1))]).astype(np.float32)
        with jax.enable_x64(True):
            state = ArmState(jnp.asarray(pad(q, [1.0, 0.0, 0.0])), jnp.asarray(pad(disk, [0.0, 0.0])))
            nxt, delta = step(state, jnp.asarray(pad(dq, [1.0, 0.0, 0.0])))
        return np.asarray(nxt.q)[:n], np.asarray(delta)[:n]

    return env, push


def jacobian(q):
    """d fingertip / d q, ``[..., 2, 3]`` (NumPy)."""
    lengths, theta = np.array(CFG.link_lengths), np.cumsum(q, -1)
    jac = np.zeros(q.shape[:-1] + (2, 3))
    for i in range(3):
        jac[..., 0, i] = -np.sum(lengths[i:] * np.sin(theta[..., i:]), -1)
        jac[..., 1, i] = np.sum(lengths[i:] * np.cos(theta[..., i:]), -1)
    return jac


def starts_near_disk(n, seed, dmax, dmin=0.0):
    """Sampled starts with the fingertip between ``max(0.32, dmin)`` and ``dmax`` from the disk."""
    near = lambda q: (jnp.linalg.norm(fingertip_xy(q, CFG)) < dmax) & (
        jnp.linalg.norm(fingertip_xy(q, CFG)) > dmin)
    keys = jax.random.split(jax.random.key(seed), n)
    return np.asarray(jax.jit(jax.vmap(lambda k: sample_arm_start(k, CFG, extra=near)))(keys))


def joint_move_for(q, v):
    """Joint moves whose first-order fingertip motion is along ``v`` ``[n, 2]``."""
    return np.einsum("bij,bj->bi", np.linalg.pinv(jacobian(q.astype(np.float64))), v)


def test_forward_kinematics_matches_mujoco(arm):
    env, _ = arm
    rng = np.random.default_rng(0)
    q = np.concatenate([rng.uniform(LO, HI, (12, 3)), [LO, HI, [0.0, 0.0, 0.0]]])
    data = mujoco.MjData(env.mj_model)
    site = mujoco.mj_name2id(env.mj_model, mujoco.mjtObj.mjOBJ_SITE, "tip")
    adr = [env.mj_model.jnt_qposadr[mujoco.mj_name2id(env.mj_model, mujoco.mjtObj.mjOBJ_JOINT, n)]
           for n in ("q1", "q2", "q3")]
    for qi in q:
        data.qpos[adr] = qi
        mujoco.mj_kinematics(env.mj_model, data)
        tip = data.site_xpos[site]
        assert abs(tip[2]) < 1e-12  # the fingertip moves in the disk centre's plane
        np.testing.assert_allclose(fingertip_xy(qi, CFG), tip[:2], atol=1e-12)
        np.testing.assert_allclose(np.asarray(env.fingertip(jnp.asarray(qi, jnp.float32))),
                                   tip[:2], atol=2e-6)
    # the model's limits are the config's
    np.testing.assert_allclose(env.mj_model.jnt_range[adr], np.stack([LO, HI], 1))


def test_disk_world_is_the_push_world(arm):
    env, _ = arm
    arm_m, push_m = env.physics_model, load_mj_model(PushConfig())
    gid = lambda m, n: mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, n)
    bid = lambda m: mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "disk")
    assert arm_m.nq == arm_m.nv == 2 and arm_m.nmocap == 1 and arm_m.npair == 1
    for field in ("dof_damping", "pair_solref", "pair_solimp", "pair_dim", "dof_armature"):
        np.testing.assert_array_equal(getattr(arm_m, field), getattr(push_m, field), err_msg=field)
    for field in ("body_mass", "body_inertia", "body_ipos", "body_iquat"):
        np.testing.assert_array_equal(getattr(arm_m, field)[bid(arm_m)],
                                      getattr(push_m, field)[bid(push_m)], err_msg=field)
    np.testing.assert_array_equal(arm_m.geom_size[gid(arm_m, "disk")], push_m.geom_size[gid(push_m, "disk")])
    np.testing.assert_array_equal(arm_m.geom_size[gid(arm_m, "fingertip")],
                                  push_m.geom_size[gid(push_m, "finger")])
    for opt in ("timestep", "iterations", "ls_iterations", "density", "jacobian", "integrator",
                "solver", "cone"):
        assert getattr(arm_m.opt, opt) == getattr(push_m.opt, opt), opt


def test_joint_limits_hold_against_pushing_moves(arm):
    _, push = arm
    # At or near a limit, moving into it: the target is clipped, the joint stops there.
    q = np.array([[0.05, 0.3, -0.4], [3.1, -1.0, 0.5], [1.2, 2.45, 0.0], [1.6, 0.0, -2.5],
                  [0.0, -2.5, 2.5]], np.float32)
    dq = np.array([[-1, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, -1], [-1, -1, 1]], np.float32)
    q1, _ = push(q, dq)
    np.testing.assert_allclose(q1[0], [0.0, 0.3, -0.4], atol=1e-6)
    np.testing.assert_allclose(q1[1], [np.pi, -1.0, 0.5], atol=1e-6)
    np.testing.assert_allclose(q1[2], [1.2, 2.5, 0.0], atol=1e-6)
    np.testing.assert_allclose(q1[4], q[4], atol=1e-6)  # already at all three limits: no move
    # Repeated random moves biased outward never leave the limits.
    rng = np.random.default_rng(3)
    q = rng.uniform(LO, HI, (BATCH, 3)).astype(np.float32)
    for _ in range(4):
        q, _ = push(q, np.sign(q - (LO + HI) / 2) + 0.3 * rng.normal(size=q.shape))
        assert np.all(q >= LO.astype(np.float32)) and np.all(q <= HI.astype(np.float32))


def test_sampled_starts_are_valid():
    keys = jax.random.split(jax.random.key(0), 4096)
    q = np.asarray(jax.jit(jax.vmap(lambda k: sample_arm_start(k, CFG)))(keys))
    tip = fingertip_xy(q.astype(np.float64), CFG)
    assert np.all(q >= LO.astype(np.float32)) and np.all(q <= HI.astype(np.float32))
    assert np.all(np.linalg.norm(tip, axis=1) > CFG.contact_distance + CFG.start_margin)
    assert np.all(np.abs(tip) <= CFG.start_range + 1e-6)
    assert np.all(q.std(0) > 0.3)  # spread over the joint box, not stuck
    behind = lambda q: fingertip_xy(q, CFG)[1] > 0.2  # behind the disk for the goal -y
    q = np.asarray(jax.vmap(lambda k: sample_arm_start(k, CFG, extra=behind))(keys[:256]))
    assert np.all(fingertip_xy(q.astype(np.float64), CFG)[:, 1] > 0.2)


def test_contact_moves_the_disk_and_moves_away_do_not(arm):
    _, push = arm
    q = starts_near_disk(6, seed=1, dmax=0.36)
    tip = fingertip_xy(q.astype(np.float64), CFG)
    inward = -tip / np.linalg.norm(tip, axis=1, keepdims=True)
    far = starts_near_disk(4, seed=2, dmax=1.5, dmin=0.55)
    dq = np.concatenate([joint_move_for(q, inward), joint_move_for(q, -inward),
                         np.random.default_rng(0).normal(size=far.shape)])
    _, delta = push(np.concatenate([q, q, far]), dq)
    moved = np.linalg.norm(delta, axis=1)
    assert np.all(moved[:6] > 0.02), moved[:6]  # toward the centre: pushed
    np.testing.assert_array_equal(delta[6:], 0.0)  # away, or far from the disk: untouched
    goals = np.linspace(-np.pi, np.pi, 16, endpoint=False)
    r = np.asarray(arm_reward(delta[:, None], goals[None]))
    assert np.all(np.any(r == 1.0, axis=1)[:6]) and np.all(r[6:] == 0.0)


def test_fingertip_moves_about_a_tenth_per_action(arm):
    _, push = arm
    keys = jax.random.split(jax.random.key(5), 20000)
    q = np.asarray(jax.jit(jax.vmap(lambda k: sample_arm_start(k, CFG)))(keys), np.float64)
    dq = np.asarray(normalize_action(jax.random.normal(jax.random.key(6), q.shape),
                                     CFG.action_length), np.float64)
    end = joint_path(q, dq, CFG)[:, -1]
    step = np.linalg.norm(fingertip_xy(end, CFG) - fingertip_xy(q, CFG), axis=1)
    print(f"fingertip displacement per action: mean {step.mean():.4f} std {step.std():.4f}")
    assert 0.09 < step.mean() < 0.11  # measured 0.099 +- 0.053 (ArmConfig.action_length)
    # the env's move is that joint path: |dq| = action_length unless a limit clips it
    q1, _ = push(q[:BATCH], dq[:BATCH] * 7.0)  # any length is rescaled
    clipped = np.any((q[:BATCH] + dq[:BATCH] < LO) | (q[:BATCH] + dq[:BATCH] > HI), axis=1)
    np.testing.assert_allclose(q1, end[:BATCH], atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(q1 - q[:BATCH], axis=1)[~clipped],
                               CFG.action_length, atol=1e-5)


def test_mjx_float64_agrees_with_native_mujoco(arm):
    env, push = arm
    q = starts_near_disk(BATCH, seed=7, dmax=0.38)
    rng = np.random.default_rng(7)
    tip = fingertip_xy(q.astype(np.float64), CFG)
    turn = np.arctan2(-tip[:, 1], -tip[:, 0]) + rng.uniform(-0.5, 0.5, BATCH)
    dq = joint_move_for(q, np.stack([np.cos(turn), np.sin(turn)], 1))
    disk = rng.uniform(-0.02, 0.02, (BATCH, 2)).astype(np.float32)
    disk[np.linalg.norm(tip - disk, axis=1) <= 0.32] = 0.0  # keep starts outside the disk
    q1, delta = push(q, dq, disk)
    native_q, native_disk = native_arm_push(env, q, disk, dq)
    assert np.sum(np.linalg.norm(delta, axis=1) > 0.01) >= 10  # most pushes touch the disk
    # Same physics model and float64 arithmetic; the fingertip path is computed
    # independently (MuJoCo's kinematics of the site "tip" vs our jnp FK, equal to
    # ~1e-16) and only the operation order differs: measured ~3e-9, far below 1e-4
    # (the reward's move threshold is 1e-2).
    np.testing.assert_allclose(disk + delta, native_disk, atol=1e-4)
    np.testing.assert_allclose(q1, native_q, atol=1e-6)


def test_deterministic(arm):
    _, push = arm
    q = starts_near_disk(BATCH, seed=3, dmax=0.5)
    dq = np.random.default_rng(3).normal(size=q.shape)
    a, b = push(q, dq), push(q, dq)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    np.testing.assert_array_equal(q, starts_near_disk(BATCH, seed=3, dmax=0.5))


def test_bad_inputs(arm):
    env, push = arm
    ok = np.array([1.2, 0.9, 1.0])
    assert np.linalg.norm(fingertip_xy(ok, CFG)) > 0.35
    with jax.enable_x64(True):
        state = env.reset(ok)
        with pytest.raises(ValueError, match="finite"):
            env.step(state, jnp.array([jnp.nan, 0.0, 1.0]))
    with pytest.raises(ValueError, match="joint limits"):
        env.reset(np.array([-0.1, 0.0, 0.0]))
    with pytest.raises(ValueError, match="shape"):
        env.reset(np.zeros(2))
    # a configuration with the fingertip inside the disk
    rng = np.random.default_rng(0)
    qs = rng.uniform(LO, HI, (20000, 3))
    inside = qs[np.linalg.norm(fingertip_xy(qs, CFG), axis=1) < 0.2][:4].astype(np.float32)
    with pytest.raises(ValueError, match="inside or touching"):
        env.reset(inside[0])
    # under jit such a start is a no-op: not simulated, nothing moves
    q1, delta = push(inside, np.ones_like(inside))
    np.testing.assert_array_equal(q1, inside)
    np.testing.assert_array_equal(delta, 0.0)
    with pytest.raises(RuntimeError, match="same precision"):  # built in x64, traced without
        jax.jit(env.step)(ArmState(jnp.asarray(ok, jnp.float32), jnp.zeros(2)), jnp.ones(3))
    for bad in ({"base_xy": (0.0, -0.5)}, {"link_lengths": (0.3, 0.2, 0.1)},
                {"joint_lower": (1.0, 0.0, 0.0), "joint_upper": (0.5, 1.0, 1.0)},
                {"action_length": 0.0}, {"link_lengths": (1.0, 1.0)}, {"start_range": 0.2}):
        with pytest.raises(ConfigError):
            ArmConfig(**bad)


def run_one(program, rule, key):
    """One seed's episodes of ``program`` under a fixed rule ``rule(s, g) -> joint moves``."""
    rollouts = run_protocol(program, seed_acts(lambda p: lambda k, s, g: rule(s, g)), jnp.zeros(1),
                            key[None])
    return jax.tree.map(lambda x: x[0], rollouts)


def test_protocol_a_for_the_arm():
    # Starts behind the disk for each goal; a policy that never moves pushes nothing, a
    # policy that always moves joint 1 (the whole arm swings) ends every episode that
    # touches the disk with an outcome the disk's displacement explains.
    env = ArmEnv(CFG)  # float32, as evaluations run
    cfg = ArmEvalConfig(n_directions=4, episodes_per_direction=3, max_steps=6)
    program = protocol_a(env, cfg, ArmCollectConfig())
    ro = run_one(program, lambda q, g: jnp.zeros_like(q), jax.random.PRNGKey(0))
    np.testing.assert_allclose(ro.agent, np.asarray(fingertip_xy(jnp.asarray(ro.extra), CFG)), atol=1e-6)
    goals = np.repeat(np.arange(4) * np.pi / 2, 3)
    tip0 = ro.agent[0]
    assert (tip0 @ np.stack([np.cos(goals), np.sin(goals)]) < 0).diagonal().all()  # behind
    assert (np.linalg.norm(tip0, axis=1) > env.config.contact_distance).all()
    assert (ro.outcome == NOT_PUSHED).all() and (ro.steps == 6).all() and (ro.idle == 6).all()
    np.testing.assert_allclose(ro.obj, 0.0)

    ro = run_one(program, lambda q, g: jnp.tile(jnp.array([1.0, 0.0, 0.0]), (q.shape[0], 1)),
                 jax.random.PRNGKey(0))
    moved = ro.outcome != NOT_PUSHED
    final = ro.obj[-1]  # frozen after the push that ended the episode (plus sub-threshold nudges)
    assert moved.any()
    cos = (final @ np.stack([np.cos(goals), np.sin(goals)])).diagonal() / np.maximum(
        np.linalg.norm(final, axis=1), 1e-12)
    agree = (cos >= 0.9) == (ro.outcome == CORRECT)
    assert (agree | (np.abs(cos - 0.9) < 0.05))[moved].all(), (cos, ro.outcome)
    assert (np.linalg.norm(final[~moved], axis=1) < env.config.push.move_threshold).all()
    assert set(np.unique(ro.outcome)) <= {NOT_PUSHED, CORRECT, WRONG}
    summary = summarize_a(ro, cfg.n_directions, cfg.episodes_per_direction)
    assert sum(r["correct"] + r["wrong"] + r["not_pushed"] for r in summary["per_goal"]) == goals.size
