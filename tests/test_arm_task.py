"""The arm tasks: their settings, arm-long's data (the disk anywhere, in the state) and its
long-horizon protocol."""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from lazyq_jax import agents, tasks
from lazyq_jax.agents import Problem
from lazyq_jax.neighbours.nd import membership_level_reference
from lazyq_jax.types import Transitions
from lazyq_jax.config import ConfigError, override
from lazyq_jax.tasks.arm import ArmCollectConfig, ArmConfig, ArmEnv, ArmEvalConfig, collect_arm, fingertip_xy
from lazyq_jax.tasks.arm.episodes import protocol_a, protocol_b
from lazyq_jax.tasks.base import CORRECT, NOT_PUSHED, WRONG, run_protocol, seed_acts

ARM = ArmConfig()
LONG = ArmCollectConfig(disk_range=0.4)


def test_arm_settings_and_their_errors():
    assert ArmCollectConfig().state_dim == 3 and LONG.state_dim == 5
    for bad in ({"disk_range": -0.1}, {"disk_range": float("nan")}, {"disk_scale": 0},
                {"explore_start": "left"}, {"n_goals": 0}):
        with pytest.raises(ConfigError):
            ArmCollectConfig(**bad)
    config = tasks.preset("arm-long")
    tasks.get("arm-long").check(config)
    with pytest.raises(ConfigError, match="exceeds collect.disk_range"):
        tasks.get("arm-long").check(override(config, ["eval.long_range=0.5"]))
    with pytest.raises(ConfigError, match="start_range"):
        override(config, ["eval.start_range=0"])
    with pytest.raises(ConfigError, match="eval.start_range=0.3 must exceed the fingertip-disk contact"):
        tasks.get("arm").check(override(tasks.preset("arm"), ["eval.start_range=0.3"]))
    # arm-long is the arm with the disk in the state: one task class, two presets; its data
    # start in its long-horizon task's boxes (disk within 0.3, fingertip within 0.6 of it),
    # protocol A in the paper's 1.0 box as the arm's
    arm = override(tasks.preset("arm"), ["collect.disk_range=0.3", "collect.arm.start_range=0.6"])
    assert arm.collect == config.collect and arm.eval == config.eval
    assert config.collect.disk_range == config.eval.long_range == 0.3
    assert config.collect.arm.start_range == config.eval.long_finger_box == 0.6
    assert config.eval.start_range == tasks.preset("arm").collect.arm.start_range == 1.0
    assert tasks.get("arm").rates[-1][0] == "overall_correct_rate"  # no long horizon without the disk
    assert tasks.get("arm-long").rates[-1][0] == "long_horizon_success_rate"
    with pytest.raises(ConfigError, match="unknown task 'crane'; known tasks: push, arm, arm-long"):
        tasks.get("crane")


def test_the_online4x_preset_is_the_measured_setting():
    """``--preset online4x`` is the setting docs/arm.md measured over 5 seeds
    (``experiments/arm_levers.py``'s ``online_fingertip_offsets_x4``: the online preset with
    the paper's 5000 starts, 1200 episodes a round, at most 40,000 moves), on both arms."""
    lever = ["neighbours.features=fingertip", "neighbours.radius_s=0.06",
             "neighbours.feature_weight=0.25", "neighbours.local_model=action+state",
             "collect.n_starts=5000", "online.episodes=1200", "online.max_moves=40000"]
    for task in ("arm", "arm-long"):
        assert tasks.preset(task, "online4x") == override(tasks.preset(task, "online"), lever)
        tasks.get(task).check(tasks.preset(task, "online4x"))


def test_the_static4x_preset_is_the_measured_setting():
    """``--preset static4x`` is the paper preset with 4x the random moves, each stored with 25
    goals instead of 100 (the rows of 1x); it is the setting docs/arm.md measured
    (``experiments/arm_levers.py``'s ``fingertip_offsets_x4_g25`` on arm and
    ``fingertip_offsets_box0.6_disk0.3_x4_g25_random`` on arm-long: there the data in the
    long-horizon task's boxes, a random joint move where the local model prefers none)."""
    four_times = ["collect.n_starts=20000", "collect.n_goals=25"]
    for task in ("arm", "arm-long"):
        assert tasks.preset(task, "static4x") == override(tasks.preset(task), four_times)
        tasks.get(task).check(tasks.preset(task, "static4x"))
    at_tip = ["neighbours.features=fingertip", "neighbours.radius_s=0.06", "neighbours.feature_weight=0.25",
              "neighbours.local_model=action+state"]
    assert tasks.preset("arm", "static4x") == override(
        tasks.preset("arm"), ["neighbours.no_model_action=zero"] + at_tip + four_times)
    measured = at_tip + ["neighbours.no_model_action=random", "collect.arm.start_range=0.6",
                         "collect.disk_range=0.3"] + four_times
    earlier_box = ["collect.arm.start_range=1.0", "collect.disk_range=0.4"]  # arm_levers' DATA_BOX
    assert tasks.preset("arm-long", "static4x") == override(tasks.preset("arm-long"), earlier_box + measured)
    assert tasks.preset("arm").neighbours.no_model_action == "zero"  # measured on arm-long only


def test_arm_long_data_put_the_disk_anywhere_in_the_state():
    cfg = ArmCollectConfig(n_starts=96, n_goals=4, chunk_size=96, disk_range=0.4)
    data = collect_arm(jax.random.PRNGKey(3), cfg, progress=False)
    s, s_next = np.asarray(data.s), np.asarray(data.s_next)
    assert s.shape[1] == s_next.shape[1] == 5 and data.a.shape[1] == 3
    disk, disk_next = s[:, 3:] / cfg.disk_scale, s_next[:, 3:] / cfg.disk_scale
    assert np.abs(disk).max() <= cfg.disk_range + 1e-6
    assert disk.std(0).min() > cfg.disk_range / 3  # spread over the square (uniform: r / sqrt 3)
    # The disk column moves only when the push moved the disk (the reward's input):
    moved = np.linalg.norm(disk_next - disk, axis=1) >= ARM.push.move_threshold
    assert ((np.asarray(data.r) != 0) <= moved).all()
    # Every push starts with the fingertip outside the disk wherever the disk is.
    tip = fingertip_xy(s[:, :3], ARM)
    assert (np.linalg.norm(tip - disk, axis=1) > ARM.contact_distance - ARM.push.finger_radius / 2).all()


def test_arm_long_horizon_task():
    """Two stand-in policies: "still" (joint moves of zero) and "swing" (joint 1 only: the
    whole arm swings)."""
    env = ArmEnv(ARM)
    cfg = ArmEvalConfig(long_rollouts=24, long_max_steps=12, success_radius=0.25, long_finger_box=0.5)
    program = protocol_b(env, cfg, LONG)
    run = lambda swing: jax.tree.map(lambda x: x[0], run_protocol(
        program, seed_acts(lambda p: lambda k, s, g: jnp.tile(jnp.array([swing, 0.0, 0.0]), (s.shape[0], 1))),
        jnp.zeros(1), jax.random.PRNGKey(1)[None]))
    # Still: only rollouts that start at their target succeed (0 steps), none moves.
    ro = run(0.0)
    disk0, target = ro.obj[0], ro.ctx
    assert np.abs(disk0).max() <= cfg.long_range and np.abs(target).max() <= cfg.long_range
    tip0 = ro.agent[0]
    np.testing.assert_allclose(tip0, np.asarray(fingertip_xy(jnp.asarray(ro.extra[0]), ARM)), atol=1e-6)
    assert (np.abs(tip0 - disk0).max(1) <= cfg.long_finger_box).all()
    assert (np.linalg.norm(tip0 - disk0, axis=1) > ARM.contact_distance).all()
    at_target = np.linalg.norm(target - disk0, axis=1) < cfg.success_radius
    assert 0 < at_target.sum() < at_target.size  # the radius makes both kinds likely
    np.testing.assert_array_equal(ro.outcome, np.where(at_target, CORRECT, NOT_PUSHED))
    np.testing.assert_array_equal(ro.steps, np.where(at_target, 0, cfg.long_max_steps))
    np.testing.assert_array_equal(ro.obj, np.broadcast_to(disk0, ro.obj.shape))
    # Swing: the outcomes are what the disk's final positions say.
    ro = run(1.0)
    final = ro.obj[-1]
    assert (np.linalg.norm(final - disk0, axis=1) > 0.01).any()  # some pushes happened
    reached = np.linalg.norm(target - final, axis=1) < cfg.success_radius
    off = np.abs(final).max(1) > ARM.push.table_half_size
    assert ((ro.outcome == CORRECT) == reached).all() and ((ro.outcome == WRONG) == (off & ~reached)).all()


def test_the_fingertip_feature_map_and_the_search_in_it():
    """The arm's ``"fingertip"`` features are the fingertip by MuJoCo's own kinematics (minus
    the disk) and the weighted joint angles; lazy Q's neighbourhoods are then exactly those
    of the mapped points (the brute-force membership levels); an identity map gives the
    neighbourhoods of the states themselves bitwise."""
    config = override(tasks.preset("arm-long", "smoke"), ["neighbours.features=fingertip",
                                                          "neighbours.feature_weight=0.5",
                                                          "neighbours.radius_s=0.08", "neighbours.k=8"])
    phi = tasks.get("arm-long").features(config)
    rng = np.random.default_rng(0)
    q = rng.uniform(ARM.joint_lower, ARM.joint_upper, (300, 3)).astype(np.float32)
    disk = rng.uniform(-0.4, 0.4, (300, 2)).astype(np.float32)
    s = np.concatenate([q, 1.2 * disk], 1)
    x = np.asarray(phi(jnp.asarray(s)))
    env = ArmEnv(ARM)
    model, data = env.mj_model, mujoco.MjData(env.mj_model)
    site = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, "tip")
    for i in range(0, 300, 37):
        data.qpos[2:5] = q[i]
        mujoco.mj_kinematics(model, data)
        np.testing.assert_allclose(x[i, :2], data.site_xpos[site, :2] - disk[i], atol=1e-5)
    np.testing.assert_allclose(x[:, 2:], 0.5 * q, rtol=1e-6)
    g = rng.uniform(-np.pi, np.pi, 300).astype(np.float32)
    trans = Transitions(s=jnp.asarray(s), a=jnp.zeros((300, 3)), s_next=jnp.asarray(s), r=jnp.zeros(300),
                        g=jnp.asarray(g), done=jnp.zeros(300, bool))
    lazy_cfg = agents.LazyConfig(train=config.train, neighbours=config.neighbours)
    agent = agents.make("lazy", lazy_cfg, problem=Problem(0.12, features=phi))
    nb = agent.prepare(0, trans, 300, 0)
    lam = membership_level_reference(x, g, x, g, radius_s=0.08, radius_g=config.neighbours.radius_g)
    level = np.sort(lam, axis=1)[:, 7]  # the k-th smallest entry level (k = 8)
    np.testing.assert_array_equal(np.asarray(nb.level), level)
    chosen = np.take_along_axis(lam, np.asarray(nb.idx), axis=1)
    assert np.all(chosen <= level[:, None])  # every sampled neighbour is a member
    # identity features: the states' own neighbourhoods, bitwise
    plain = agents.make("lazy", lazy_cfg, problem=Problem(0.12)).prepare(0, trans, 300, 0)
    same = agents.make("lazy", lazy_cfg, problem=Problem(0.12, features=lambda v: v)).prepare(0, trans, 300, 0)
    np.testing.assert_array_equal(np.asarray(plain.idx), np.asarray(same.idx))


def test_protocol_a_starts_in_its_own_box_whatever_box_the_data_used():
    """``eval.start_range`` bounds protocol A's fingertip starts (the paper's 1.0 by default);
    the data's ``collect.arm.start_range`` does not move them: the same episodes bitwise."""
    still = seed_acts(lambda p: lambda k, s, g: jnp.zeros((s.shape[0], 3)))
    cfg = ArmEvalConfig(n_directions=4, episodes_per_direction=16, max_steps=1)

    def starts(eval_cfg, data_box):
        arm = ArmConfig(start_range=data_box)
        program = protocol_a(ArmEnv(arm), eval_cfg, ArmCollectConfig(arm=arm))
        ro = run_protocol(program, still, jnp.zeros(1), jax.random.PRNGKey(2)[None])
        return np.asarray(ro.agent[0, 0])  # [episodes, 2] fingertips at the start

    paper = starts(cfg, 1.0)
    np.testing.assert_array_equal(starts(cfg, 0.6), paper)  # the data's box is set apart
    assert np.abs(paper).max() <= 1.0 and np.abs(paper).max() > 0.6  # the whole box is used
    near = starts(ArmEvalConfig(n_directions=4, episodes_per_direction=16, max_steps=1,
                                start_range=0.6), 1.0)
    assert np.abs(near).max() <= 0.6 and (np.linalg.norm(near, axis=1) > ARM.contact_distance).all()
