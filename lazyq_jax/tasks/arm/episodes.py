"""The arm's episodes: its random data (§V-A-3 in joint space), protocol A and the
long-horizon task in joint space (§V-B), and its online rounds.

The action is a joint move ``dq`` of norm ``ArmConfig.action_length`` (``n_a = 3``); the
goal is the push direction angle, the reward Eq. (15) of the disk's displacement.  As
for the finger: ``n_starts`` random collision-free starts (:func:`sample_arm_start`),
``moves_per_start`` moves in one random joint direction, ``n_goals`` fresh goals per
move, and an episode ends at a push that moves the disk.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from jax.sharding import Mesh

from lazyq_jax.agents.base import Act
from lazyq_jax.config import Config
from lazyq_jax.data import episodes_to_transitions, run_episodes
from lazyq_jax.tasks.arm.config import ArmCollectConfig, ArmEvalConfig
from lazyq_jax.tasks.arm.env import ArmEnv, ArmState, fingertip_xy, sample_arm_start
from lazyq_jax.tasks.base import Protocol, make_protocol
from lazyq_jax.tasks.push.explore import episode_counts
from lazyq_jax.tasks.push.collect import repeated_moves
from lazyq_jax.tasks.push.protocols import direction_outcome, directions, long_horizon
from lazyq_jax.tasks.push.reward import disk_moved, push_reward
from lazyq_jax.tasks.push.scripted import scripted_push_policy
from lazyq_jax.types import Transitions


def observer(config: ArmCollectConfig):
    """``observe(state) -> s``: the joint angles, then the scaled disk position if
    ``config.disk_in_state``."""
    if not config.disk_in_state:
        return lambda state: state.q
    return lambda state: jnp.concatenate([state.q, config.disk_scale * state.disk_xy], -1)


def fingertip_features(config: ArmCollectConfig, w: float):
    """``phi(s) -> (fingertip - disk, w q)`` (``[..., 5]``; ``[..., 2]`` for ``w = 0``): the
    fingertip by forward kinematics, relative to the disk (the origin, or the disk of the
    state), and the joint angles, weighted, which tell the redundant arm's
    configurations (and so their Jacobians) apart."""
    arm = config.arm

    def phi(s):
        tip = fingertip_xy(s[..., :3], arm)
        if config.disk_in_state:
            tip = tip - s[..., 3:5] / config.disk_scale
        return tip if w == 0 else jnp.concatenate([tip, w * s[..., :3]], -1)

    return phi


def state_scale(config: ArmCollectConfig) -> tuple[float, ...]:
    """Per-dimension input scale of the networks: the joint limits' half-ranges (and the
    disk coordinates' range in state units)."""
    arm = config.arm
    joints = tuple((hi - lo) / 2 for lo, hi in zip(arm.joint_lower, arm.joint_upper))
    return joints + ((config.disk_scale * config.disk_range,) * 2 if config.disk_in_state else ())


def _random_direction(key, n: int = 3) -> jax.Array:
    d = jax.random.normal(key, (n,), jnp.float32)
    return d / jnp.linalg.norm(d)


def make_episode_fn(env: ArmEnv, config: ArmCollectConfig):
    """``episode(key) -> dict`` of one random joint-space episode, unbatched (vmap it)."""
    arm, observe = env.config, observer(config)

    def episode(key):
        # Three keys with the disk at the origin: the arm task's data as before arm-long.
        k_start, k_dir, k_goal, *k_disk = jax.random.split(key, 4 if config.disk_in_state else 3)
        disk = (jnp.zeros(2, jnp.float32) if not config.disk_in_state else
                jax.random.uniform(k_disk[0], (2,), jnp.float32, -config.disk_range, config.disk_range))
        q0 = sample_arm_start(k_start, arm, disk_xy=disk)
        action = arm.action_length * _random_direction(k_dir)
        return repeated_moves(env.step, env.reset(q0, disk), action, k_goal, config, arm.push,
                              observe=observe)

    return episode


def collect_arm(key: jax.Array, config: ArmCollectConfig = ArmCollectConfig(), *,
                mesh: Mesh | None = None, progress: bool = True) -> Transitions:
    """Random joint-space pushes of the arm, relabelled for ``config.n_goals`` goals per move.

    Returns ``Transitions`` with ``s, s_next: [N, config.state_dim]`` (joint angles, then
    the scaled disk position if ``config.disk_in_state``), ``a: [N, 3]`` the chosen joint
    moves (the env shortens moves that would leave the joint limits), ``g: [N]`` goal
    angles; physics in float64 when ``config.arm.push.float64``.
    """
    if not isinstance(config, ArmCollectConfig):
        raise TypeError(f"collect_arm needs an ArmCollectConfig, got {type(config).__name__}")
    make = lambda: make_episode_fn(ArmEnv(config.arm), config)
    eps = run_episodes(key, make, ("arm", config), config.n_starts, config.chunk_size,
                       float64=config.arm.push.float64, mesh=mesh, progress=progress,
                       desc="collect arm (episodes)")
    return episodes_to_transitions(eps, config.n_goals)


def protocol_a(env: ArmEnv, cfg: ArmEvalConfig, collect: ArmCollectConfig) -> Protocol:
    """Protocol A (Fig. 4) for the arm: push the disk at the origin toward each of
    ``cfg.n_directions`` goals, ``cfg.episodes_per_direction`` episodes each.

    Starts: :func:`sample_arm_start` conditioned on the fingertip being behind the disk
    (``fingertip . goal_direction < 0``) and within ``cfg.start_range`` of it, as the
    finger's (whatever box the data started in); outcomes as the finger's
    (:func:`lazyq_jax.tasks.push.protocols.direction_outcome`).  The rollouts draw the
    fingertip (``agent``) and keep the joint angles (``extra``).
    """
    arm = env.config
    starts = dataclasses.replace(arm, start_range=cfg.start_range)
    goals = jnp.repeat(directions(cfg.n_directions), cfg.episodes_per_direction)

    def start(key):
        def one(k, g):
            behind = lambda q: fingertip_xy(q, arm) @ jnp.stack([jnp.cos(g), jnp.sin(g)]) < 0
            return sample_arm_start(k, starts, extra=behind)

        q0 = jax.vmap(one)(jax.random.split(key, goals.shape[0]), goals)
        return env.reset(q0), goals, jnp.zeros(goals.shape, bool)

    outcome = direction_outcome(arm.push.cos_threshold, arm.push.move_threshold)
    return make_protocol(start, jax.vmap(env.step), lambda st, goals: goals,
                         lambda delta, g, new, ctx: outcome(delta, g, new), observer(collect),
                         lambda st: (fingertip_xy(st.q, arm), st.disk_xy, st.q), cfg.max_steps)


def protocol_b(env: ArmEnv, cfg: ArmEvalConfig, collect: ArmCollectConfig) -> Protocol:
    """The long-horizon task (Fig. 5) for the arm (``collect.disk_in_state`` only): disk and
    target uniform in ``[-long_range, long_range]^2``, the arm's start with the fingertip
    outside the disk within ``long_finger_box`` of it, the high-level controller and
    outcomes of :func:`lazyq_jax.tasks.push.protocols.long_horizon`; the targets are the
    rollouts' ``ctx``."""
    arm = env.config
    b, lim = cfg.long_rollouts, cfg.long_range
    near = dataclasses.replace(arm, start_range=cfg.long_finger_box)

    def start(key):
        k_disk, k_target, k_start = jax.random.split(key, 3)
        disk = jax.random.uniform(k_disk, (b, 2), jnp.float32, -lim, lim)
        target = jax.random.uniform(k_target, (b, 2), jnp.float32, -lim, lim)
        q0 = jax.vmap(lambda k, d: sample_arm_start(k, near, disk_xy=d))(jax.random.split(k_start, b),
                                                                         disk)
        return env.reset(q0, disk), target

    return long_horizon(start, jax.vmap(env.step), cfg, arm.push.table_half_size,
                        observe=observer(collect),
                        record=lambda st: (fingertip_xy(st.q, arm), st.disk_xy, st.q))


def explore_round(act: Act, key: jax.Array, config: Config) -> dict:
    """One online round of the arm (pure; the runner vmaps it over seeds): ``online.episodes``
    episodes of at most ``online.max_steps`` joint moves from starts like protocol A's
    (the disk where the data's start, the fingertip behind it for the episode's goal, or
    anywhere); per move a random joint direction with probability ``epsilon`` or where
    the agent gives no move, else the agent's direction with Gaussian noise of
    ``action_noise`` per component (renormalised: turned by about that many radians
    per dimension).  Relabelled for ``collect.n_goals`` goals; an episode ends at the
    first push that moves the disk.  Output as
    :func:`lazyq_jax.tasks.push.explore.explore_round`."""
    c, o = config.collect, config.online
    arm = c.arm
    env, observe = ArmEnv(arm), observer(c)
    b = o.episodes
    k_goal, k_disk, k_start, k_run, k_label = jax.random.split(key, 5)
    goals = jax.random.uniform(k_goal, (b,), jnp.float32, -jnp.pi, jnp.pi)
    disk = (jnp.zeros((b, 2), jnp.float32) if not c.disk_in_state else
            jax.random.uniform(k_disk, (b, 2), jnp.float32, -c.disk_range, c.disk_range))

    def start(k, g, d):
        behind = None if c.explore_start == "anywhere" else (
            lambda q: (fingertip_xy(q, arm) - d) @ jnp.stack([jnp.cos(g), jnp.sin(g)]) < 0)
        return sample_arm_start(k, arm, extra=behind, disk_xy=d)

    q0 = jax.vmap(start)(jax.random.split(k_start, b), goals, disk)
    step = jax.vmap(env.step)

    def move(carry, k):
        state, done = carry
        k_pol, k_eps, k_dir, k_noise = jax.random.split(k, 4)
        s = observe(state)
        greedy = act(k_pol, s, goals)
        norm = jnp.linalg.norm(greedy, axis=-1, keepdims=True)
        found = norm[:, 0] > 0
        direction = greedy / jnp.where(norm > 0, norm, 1.0)
        direction = direction + o.action_noise * jax.random.normal(k_noise, direction.shape)
        explore = (jax.random.uniform(k_eps, (b,)) < o.epsilon) | ~found
        direction = jnp.where(explore[:, None], jax.vmap(_random_direction)(jax.random.split(k_dir, b)),
                              direction)
        action = arm.action_length * direction / jnp.linalg.norm(direction, axis=-1, keepdims=True)
        new, delta = step(state, action)
        live = ~done
        delta = jnp.where(live[:, None], delta, 0.0)
        moved = disk_moved(delta, arm.push.move_threshold)
        state = jax.tree.map(lambda n, old: jnp.where(live[:, None], n, old), new, state)
        return (state, done | moved), (s, action, observe(state), delta, moved)

    init = (env.reset(q0, disk), jnp.zeros(b, bool))
    _, out = jax.lax.scan(move, init, jax.random.split(k_run, o.max_steps))
    s, a, s_next, delta, moved = (jnp.swapaxes(x, 0, 1) for x in out)
    labels = jax.random.uniform(k_label, (b, o.max_steps, c.n_goals), jnp.float32, -jnp.pi, jnp.pi)
    reward = push_reward(delta[:, :, None, :], labels, move_threshold=arm.push.move_threshold,
                         cos_threshold=arm.push.cos_threshold)
    return {"s": s, "a": a, "s_next": s_next, "moved": moved, "g": labels, "r": reward,
            "goal": goals, "counts": episode_counts(delta, moved, goals, arm.push.cos_threshold)}


def scripted_arm_policy(config: ArmCollectConfig, damping: float = 1e-4):
    """The push task's scripted controller (:func:`lazyq_jax.tasks.push.scripted.scripted_push_policy`)
    moved to joint space: the fingertip direction it chooses for the fingertip relative to
    the disk, turned into a joint move by the damped pseudo-inverse of the arm's Jacobian
    ``J^T (J J^T + damping I)^-1`` and scaled to ``action_length``.  It knows the physics and
    the kinematics and learns nothing: an upper reference for the arm."""
    arm = config.arm
    finger = scripted_push_policy(arm.push)
    jacobian = jax.vmap(jax.jacfwd(lambda q: fingertip_xy(q, arm)))

    def act(key, s, g):
        q = s[:, :3]
        disk = s[:, 3:5] / config.disk_scale if config.disk_in_state else 0.0
        direction = finger(key, fingertip_xy(q, arm) - disk, g)  # [B, 2]
        jac = jacobian(q)  # [B, 2, 3]
        gram = jac @ jnp.swapaxes(jac, 1, 2) + damping * jnp.eye(2)
        dq = jnp.einsum("bij,bj->bi", jnp.swapaxes(jac, 1, 2), jnp.linalg.solve(gram, direction[..., None])[..., 0])
        norm = jnp.linalg.norm(dq, axis=-1, keepdims=True)
        return arm.action_length * dq / jnp.maximum(norm, 1e-12)

    return act


def disk_at_origin(collect: ArmCollectConfig):
    """``state_of(q [n, 3]) -> s``: the agent's states with the disk at the origin."""
    observe = observer(collect)
    return lambda q: observe(ArmState(q, jnp.zeros(q.shape[:-1] + (2,), q.dtype)))
