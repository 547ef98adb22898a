"""The arm task's data: random joint-space pushes (§V-A-3 in joint space), relabelled for goals.

The state is the joint angles ``q`` (``d_s = 3``) with the disk at its start position
(the origin) for every push; the action is a joint move ``dq`` of norm
``ArmConfig.action_length`` (``n_a = 3``); the goal is the push direction angle, the
reward Eq. (15) of the disk's displacement.  As for the finger: ``n_starts`` random
collision-free starts (:func:`lazyq_jax.env.arm.sample_arm_start`), ``moves_per_start``
moves in one random joint direction, ``n_goals`` fresh goals per move, and an episode
ends at a push that moves the disk.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax.sharding import Mesh

from lazyq_jax.config import CollectConfig, EvalConfig
from lazyq_jax.data import episodes_to_transitions, run_episodes
from lazyq_jax.env.arm import ArmConfig, ArmEnv, fingertip_xy, sample_arm_start
from lazyq_jax.env.reward import disk_moved, push_reward
from lazyq_jax.evaluate import Act, Rollouts, _directions, _rollout, direction_outcome
from lazyq_jax.types import Transitions


def make_arm_episode_fn(env: ArmEnv, config: CollectConfig):
    """``episode(key) -> dict`` of one random joint-space episode, unbatched (vmap it)."""
    arm, pc = env.config, env.config.push

    def episode(key):
        k_start, k_dir, k_goal = jax.random.split(key, 3)
        q0 = sample_arm_start(k_start, arm)
        direction = jax.random.normal(k_dir, (3,), jnp.float32)
        action = arm.action_length * direction / jnp.linalg.norm(direction)
        goals = jax.random.uniform(k_goal, (config.moves_per_start, config.n_goals), jnp.float32,
                                   -jnp.pi, jnp.pi)

        def move(state, _):
            nxt, delta = env.step(state, action)
            return nxt, (state.q, nxt.q, delta)

        _, (s, s_next, delta) = jax.lax.scan(move, env.reset(q0), None,
                                             length=config.moves_per_start)
        reward = push_reward(delta[:, None, :], goals, move_threshold=pc.move_threshold,
                             cos_threshold=pc.cos_threshold)
        return {"s": s, "a": jnp.broadcast_to(action, s.shape), "s_next": s_next, "delta": delta,
                "g": goals, "r": reward, "moved": disk_moved(delta, pc.move_threshold)}

    return episode


def collect_arm(key: jax.Array, arm: ArmConfig = ArmConfig(),
                config: CollectConfig = CollectConfig(), *, mesh: Mesh | None = None,
                progress: bool = True) -> Transitions:
    """Random joint-space pushes of the arm, relabelled for ``config.n_goals`` goals per move
    (``config.start_range`` and ``config.push`` are not used: the arm's own are).

    Returns ``Transitions`` with ``s, s_next: [N, 3]`` joint angles, ``a: [N, 3]`` the
    chosen joint moves (the env shortens moves that would leave the joint limits), ``g:
    [N]`` goal angles; physics in float64 when ``arm.push.float64``.
    """
    if not isinstance(arm, ArmConfig) or not isinstance(config, CollectConfig):
        raise TypeError("collect_arm needs an ArmConfig and a CollectConfig")
    make = lambda: make_arm_episode_fn(ArmEnv(arm), config)
    eps = run_episodes(key, make, ("arm", arm, config), config.n_starts, config.chunk_size,
                       float64=arm.push.float64, mesh=mesh, progress=progress,
                       desc="collect arm (episodes)")
    return episodes_to_transitions(eps, config.n_goals)


def arm_protocol_a(env: ArmEnv, act: Act, key: jax.Array, cfg: EvalConfig) -> Rollouts:
    """Protocol A (Fig. 4) for the arm: push the disk at the origin toward each of
    ``cfg.n_directions`` goals, ``cfg.episodes_per_direction`` episodes each.

    Starts: :func:`sample_arm_start` conditioned on the fingertip being behind the disk
    (``fingertip . goal_direction < 0``), as the finger's starts in
    :func:`lazyq_jax.evaluate.protocol_a`; ``act(key, q[B, 3], g[B])`` gives joint moves.
    Outcomes as there (:func:`lazyq_jax.evaluate.direction_outcome`); ``Rollouts.finger``
    holds the fingertip.  Summarise with :func:`lazyq_jax.evaluate.summarize_a`.
    """
    arm = env.config
    goals = jnp.repeat(_directions(cfg.n_directions), cfg.episodes_per_direction)
    k_start, k_run = jax.random.split(key)

    def start(k, g):
        behind = lambda q: fingertip_xy(q, arm) @ jnp.stack([jnp.cos(g), jnp.sin(g)]) < 0
        return sample_arm_start(k, arm, extra=behind)

    q0 = jax.vmap(start)(jax.random.split(k_start, goals.shape[0]), goals)
    state = env.reset(q0)
    outcome_of = direction_outcome(arm.push.cos_threshold, arm.push.move_threshold)
    return _rollout(env, act, k_run, state, lambda st: goals, cfg.max_steps, outcome_of,
                    jnp.zeros(goals.shape, bool), observe=lambda st: st.q,
                    finger_of=lambda st: fingertip_xy(st.q, arm))
