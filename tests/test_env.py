"""Physics expectations for the push scene, independent of how it is implemented."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lazyq_jax.tasks.push import FORGIVING_PUSH, PushConfig, PushEnv, push_reward
from lazyq_jax.tasks.push.env import coulomb_friction, normalize_action
from lazyq_jax.tasks.push.native import native_push
from lazyq_jax.tasks.sampling import sample_outside_disk

AXES = np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])


def angle_deg(v):
    return np.degrees(np.arctan2(v[..., 1], v[..., 0]))


@pytest.mark.parametrize("world", ["push", "push_forgiving"])
def test_axis_push_toward_centre_moves_disk_along_axis(world, request):
    push = request.getfixturevalue(world)
    start = -0.33 * AXES  # just outside touching distance 0.31, aimed at the centre
    _, delta = push(start, AXES)
    along = np.sum(delta * AXES, axis=1)
    across = np.abs(delta[:, 0] * AXES[:, 1] - delta[:, 1] * AXES[:, 0])
    assert np.all(along > 0.05), along  # most of the 0.1 move is passed on to the disk
    assert np.all(along < 0.1 + 1e-3), along  # but the disk cannot outrun the finger by much
    assert np.all(across < 1e-4), across
    goals = np.arctan2(AXES[:, 1], AXES[:, 0])
    assert np.all(np.asarray(push_reward(delta, goals)) == 1.0)
    assert np.all(np.asarray(push_reward(delta, goals + np.pi)) == -1.0)


def head_on(push, degrees):
    """Head-on pushes (aimed at the centre) at these angles: the moved direction in degrees."""
    angles = np.radians(np.asarray(degrees, float))
    d = np.stack([np.cos(angles), np.sin(angles)], 1)
    _, delta = push(-0.33 * d, d)
    assert np.all(np.linalg.norm(delta, axis=1) > 0.05)
    return angle_deg(delta)


def toward_nearer_axis(pushed, moved):
    """Deflection of ``moved`` from ``pushed`` (degrees), positive toward the nearer axis."""
    deflection = (np.asarray(moved) - pushed + 180) % 360 - 180
    return deflection * np.sign(np.round(np.asarray(pushed) / 90) * 90 - pushed)


def test_paper_world_snaps_pushes_onto_the_axes(push):
    # Coulomb friction per table axis: the force across the nearer axis stays below
    # the friction, so the disk slides along that axis (paper Fig. 2b, strongly).
    pushed = np.array([30.0, 60.0, 120.0, 210.0, -30.0, -150.0, 10.0, -80.0])
    moved = head_on(push, pushed)
    axis = np.round(pushed / 90) * 90
    assert np.all(np.abs((moved - axis + 180) % 360 - 180) < 3), moved
    # 1 degree off a diagonal is already deflected by > 10 degrees toward the nearer axis
    # (the diagonal itself is an unstable equilibrium).
    near = np.array([44.0, 46.0, 136.0, -134.0])
    assert np.all(toward_nearer_axis(near, head_on(push, near)) > 10)


def test_forgiving_world_deflects_off_diagonal_pushes(push_forgiving):
    # Quadratic drag in the 45-degree frame: a head-on push 5 degrees off a diagonal
    # drifts toward the nearer axis by about 14 degrees (PushConfig docstring).
    pushed = np.array([40.0, 50.0, 130.0, 220.0, -40.0, -130.0])
    deflection = toward_nearer_axis(pushed, head_on(push_forgiving, pushed))
    assert np.all((deflection > 10) & (deflection < 20)), deflection


@pytest.mark.parametrize("world", ["push", "push_forgiving"])
def test_axis_pushes_are_forgiving_diagonal_pushes_are_not(world, request):
    # Same 20-degree error in the push direction: along an axis the disk still moves
    # within the goal's cone (reward +1), along a diagonal it does not.
    push = request.getfixturevalue(world)
    err = np.radians(20.0)
    angles = np.array([0.0, np.pi / 2, np.pi / 4, 3 * np.pi / 4])
    d = np.stack([np.cos(angles + err), np.sin(angles + err)], 1)
    _, delta = push(-0.33 * d, d)
    r = np.asarray(push_reward(delta, angles))
    np.testing.assert_array_equal(r, [1.0, 1.0, -1.0, -1.0])


def test_coulomb_linearisation_matches_the_friction_law():
    """``coulomb_friction`` returns MuJoCo's implicit damping and explicit force such that
    ``force - damping * v`` is the friction ``F(v)`` and ``damping = -F'(v)``."""
    cfg = PushConfig()
    mu, eps, c = cfg.friction_coefficient, cfg.friction_smoothing, cfg.damping
    law = lambda v: -mu * v / np.sqrt(v * v + eps * eps) - c * v
    v = np.array([-0.3, -0.02, -1e-3, 0.0, 2e-4, 0.004, 0.05, 0.25])
    damping, force = coulomb_friction(v, cfg)
    np.testing.assert_allclose(force - damping * v, law(v), rtol=1e-12, atol=1e-15)
    h = 1e-7  # central difference; F is smooth on the scale eps = 5e-3 >> h
    np.testing.assert_allclose(damping, -(law(v + h) - law(v - h)) / (2 * h), rtol=1e-5)
    assert np.all(damping >= c)  # never negative damping: the implicit step is stable


def test_move_away_from_disk_does_not_move_it(push):
    rng = np.random.default_rng(0)
    ang = rng.uniform(-np.pi, np.pi, 8)
    start = 0.5 * np.stack([np.cos(ang), np.sin(ang)], 1)
    away = start / np.linalg.norm(start, axis=1, keepdims=True)
    tangent = np.stack([-away[:, 1], away[:, 0]], 1)
    far = np.array([[0.9, -0.9]]).repeat(4, 0)
    finger, delta = push(np.concatenate([start[:4], start[4:], far]),
                         np.concatenate([away[:4], tangent[4:], rng.normal(size=(4, 2))]))
    assert np.all(np.linalg.norm(delta, axis=1) < 1e-6)
    goals = np.linspace(-np.pi, np.pi, 16, endpoint=False)
    assert np.all(np.asarray(push_reward(delta[:, None, :], goals[None, :])) == 0.0)


def test_finger_ends_action_length_from_start(push):
    start = np.array([[0.9, 0.9], [-0.6, 0.5], [-0.35, 0.0], [0.0, -0.8]])
    action = np.array([[3.0, 4.0], [1e-3, 0.0], [1.0, 0.0], [-0.02, 0.5]])  # any length
    finger, _ = push(start, action)
    np.testing.assert_allclose(np.linalg.norm(finger - start, axis=1), 0.1, atol=1e-6)
    unit = action / np.linalg.norm(action, axis=1, keepdims=True)
    np.testing.assert_allclose(finger - start, 0.1 * unit, atol=1e-6)


def _contact_pushes(n=16, seed=1):
    rng = np.random.default_rng(seed)
    ang = rng.uniform(-np.pi, np.pi, n)
    start = rng.uniform(0.32, 0.42, n)[:, None] * np.stack([np.cos(ang), np.sin(ang)], 1)
    turn = ang + np.pi + rng.uniform(-0.6, 0.6, n)  # roughly toward the disk
    disk = rng.uniform(-0.3, 0.3, (n, 2))
    return ((start + disk).astype(np.float32), np.stack([np.cos(turn), np.sin(turn)], 1),
            disk.astype(np.float32))


@pytest.mark.parametrize("world", ["paper", "forgiving"])
def test_mjx_float64_agrees_with_native_mujoco(world):
    finger, action, disk = _contact_pushes()
    config = PushConfig() if world == "paper" else FORGIVING_PUSH
    with jax.enable_x64(True):
        env = PushEnv(config)
        assert env.dtype == jnp.float64
        _, delta = jax.jit(jax.vmap(env.step))(env.reset(finger, disk), jnp.asarray(action))
        delta = np.asarray(delta)
    native = native_push(env, finger, disk, action)
    assert np.mean(np.linalg.norm(delta, axis=1) > 0.01) > 0.5  # the check is not vacuous
    # Same model, same float64 arithmetic up to operation order: far below 1e-4 (measured
    # ~1e-8; the reward's move threshold is 1e-2).
    np.testing.assert_allclose(disk + delta, native, atol=1e-4)


@pytest.mark.parametrize("world, atol", [("push", 1e-4), ("push_forgiving", 5e-3)])
def test_mjx_float32_is_close_to_native(world, atol, request):
    # float32 rounding (~1e-7 of a position) over 55 substeps; the forgiving world's
    # deflection dynamics amplify it to mm (README), the paper world's friction does not.
    push = request.getfixturevalue(world)
    env = PushEnv(PushConfig() if world == "push" else FORGIVING_PUSH)
    finger, action, disk = _contact_pushes()
    _, delta = push(finger, action, disk)
    np.testing.assert_allclose(disk + delta, native_push(env, finger, disk, action), atol=atol)


def test_precision_mismatch_is_an_error(env):
    with jax.enable_x64(True):
        with pytest.raises(RuntimeError, match="same precision"):
            jax.jit(env.step)(env.reset(jnp.array([0.8, 0.0])), jnp.array([1.0, 0.0]))


def test_bad_actions_and_starts(env):
    state = env.reset(jnp.array([0.8, 0.0]))
    with pytest.raises(ValueError, match="finite"):
        env.step(state, jnp.array([jnp.nan, 1.0]))
    with pytest.raises(ValueError, match="inside or touching"):
        env.reset(jnp.array([0.2, 0.0]))
    with pytest.raises(ValueError, match="inside or touching"):
        env.reset(jnp.array([0.31, 0.0]))  # exactly touching
    with pytest.raises(ValueError, match="shape"):
        env.reset(jnp.zeros(3))
    # inside jit a non-finite action is a no-op, never NaN
    np.testing.assert_array_equal(
        np.asarray(normalize_action(jnp.array([[jnp.inf, 0.0], [0.0, 0.0], [0.0, 2.0]]), 0.1)),
        np.array([[0.0, 0.0], [0.0, 0.0], [0.0, 0.1]], np.float32))
    # and a finger placed inside the disk under jit is pushed out, not simulated inside
    f = jax.jit(env.reset)(jnp.array([0.1, 0.0]), jnp.zeros(2)).finger_xy
    assert np.linalg.norm(np.asarray(f)) > env.config.contact_distance


def test_sample_outside_disk_is_uniform_on_allowed_region():
    keys = jax.random.split(jax.random.key(0), 20000)
    x = np.asarray(jax.jit(jax.vmap(lambda k: sample_outside_disk(k, jnp.zeros(2), 1.0, 0.31)))(keys))
    assert np.all(np.linalg.norm(x, axis=1) > 0.31) and np.all(np.abs(x) <= 1.0)
    # uniform: the ring 0.31 < r < 0.6 holds area pi (0.6^2 - 0.31^2) of 4 - pi 0.31^2
    frac = np.mean(np.linalg.norm(x, axis=1) < 0.6)
    expected = np.pi * (0.6**2 - 0.31**2) / (4 - np.pi * 0.31**2)
    assert abs(frac - expected) < 0.02, (frac, expected)


class TestReward:
    def test_table(self):
        g = np.array([0.0, 0.0, 0.0, 0.0, 0.0, np.pi / 2, np.pi])
        delta = np.array([
            [0.0, 0.0],        # not moved
            [0.00999, 0.0],    # just below the move threshold
            [0.01, 0.0],       # exactly at the threshold: moved, correct
            [-0.05, 0.0],      # moved, opposite direction
            [0.05, 0.05],      # moved, 45 degrees off: cos 0.707 -> wrong
            [0.0, 0.2],        # moved along +y, goal +y
            [-0.3, 0.0],       # moved along -x, goal pi
        ])
        np.testing.assert_array_equal(np.asarray(push_reward(delta, g)), [0, 0, 1, -1, -1, 1, 1])

    def test_cos_boundary(self):
        # Eq. (15) demands cos > 0.9: just above is correct, just below is wrong.
        theta = np.arccos(0.9)
        for eps, expected in [(-1e-3, 1.0), (1e-3, -1.0)]:
            d = 0.05 * np.array([np.cos(theta + eps), np.sin(theta + eps)])
            assert float(push_reward(d, 0.0)) == expected
        # the goal is periodic: -pi and pi are the same direction
        assert float(push_reward(np.array([-0.05, 0.0]), -np.pi)) == 1.0

    def test_broadcast_and_dtype(self):
        r = push_reward(np.zeros((3, 1, 2)), np.zeros(5))
        assert r.shape == (3, 5) and r.dtype == jnp.float32
