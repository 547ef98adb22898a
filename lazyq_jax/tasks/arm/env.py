"""A planar 3-link arm that pushes the disk in joint space: the second task's physics.

The disk world is the push task's (:class:`PushConfig`, by default the paper's
world: Coulomb friction per table axis via :func:`coulomb_friction`, one
frictionless fingertip-disk contact pair, quasistatic moves of ``move_substeps``
+ ``settle_substeps``).  What changes is the agent: its state is the arm's joint
angles ``q`` (``d_s = 3``), its action a joint move ``dq`` of norm
``action_length`` radians (``n_a = 3``), its goal the push direction angle
(rewarded by :func:`lazyq_jax.tasks.push.reward.push_reward`, Eq. 15).

Geometry (:class:`ArmConfig` defaults): base at ``(0, -1)``, 0.25 outside the
1.5 x 1.5 table; links 0.9, 0.7, 0.4 (reach 2.0); joint ranges ``q1 in [0, pi]``
(the arm points into the table's half plane), ``q2, q3 in [-2.5, 2.5]``.  The
fingertip reaches all around the disk's ring 0.35-0.7 (far side 1.7 from the base,
85 % of the reach, so the arm is not stretched into the singular straight pose
there: near each of 72 points on the rings 0.35, 0.5 and 0.7 some configuration
0.25 rad inside the limits has the Jacobian's smaller singular value >= 0.45) and
folds down to the near side (0.3 from the base).  ``q = 0`` points the arm
along +x; the fingertip is ``base + sum_i l_i (cos th_i, sin th_i)`` with
``th_i = q_1 + ... + q_i``.

Kinematic arm (the choice): the arm is position-controlled and perfectly stiff.
Each push interpolates the joints linearly from ``q`` to the target in
``move_substeps`` equal steps and holds them for ``settle_substeps``; a mocap
fingertip follows the forward kinematics of the interpolated angles.  This is
the push task's physics exactly (its mocap finger now moves on a slightly curved
path), with no arm dynamics to simulate: the simulated model is the scene
without the arm's bodies (disk, mocap fingertip, table; 2 dofs), so an arm push
costs about what a finger push costs (static arm bodies would still cost MJX
their kinematics every substep: measured 10k instead of 17k pushes/s at batch
1024 on 2 CPU cores).  The links collide with nothing and pass over the disk, as
a planar arm above the table would; only the fingertip touches it.

Joint limits: the target ``q + dq`` is clipped to the limits (the straight
joint path then stays inside them, which are a box); a move against a limit is
shortened, possibly to nothing.

A fingertip that starts deep inside the disk (closer than ``contact_distance -
finger_radius / 2`` to its centre; pushes leave it at most a few mm inside)
is never simulated: :meth:`ArmEnv.reset` raises outside ``jit`` for any start
inside or touching the disk, and :meth:`ArmEnv.step` from such a state is a no-op
(no move, disk still), since under ``jit`` nothing can raise.  The disk resets to
its start after a push that moves it, where the episode ends (reward != 0): the
fingertip may then lie inside the reset disk, so collectors must not step on.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import importlib.resources
import io
import math
from collections.abc import Callable

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct

with contextlib.redirect_stdout(io.StringIO()):
    from mujoco import mjx

from lazyq_jax.config import ConfigError
from lazyq_jax.tasks.push.config import PushConfig
from lazyq_jax.tasks.push.env import _is_concrete, _x64, apply_push_config, coulomb_friction, normalize_action
from lazyq_jax.tasks.push.reward import push_reward
from lazyq_jax.tasks.sampling import rejection_sample

_SCENE = "arm.xml"
ARM_JOINTS = ("q1", "q2", "q3")
_LINKS = ("link1", "link2", "link3")


def _check(cond: bool, msg: str) -> None:
    if not cond:
        raise ConfigError(msg)


def _floats(value, n: int, name: str) -> tuple[float, ...]:
    ok = (isinstance(value, (tuple, list)) and len(value) == n
          and all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                  for v in value))
    _check(ok, f"ArmConfig.{name} must be {n} finite numbers, got {value!r}")
    return tuple(float(v) for v in value)


@dataclasses.dataclass(frozen=True)
class ArmConfig:
    """The arm-pushes-disk scene (see the module docstring for the geometry).

    Attributes:
      push: the disk, table, fingertip radius, friction, substeps and reward
        thresholds: the push task's world (default: the paper's).  Its
        ``action_length`` (a finger move) is not used; ``finger_radius`` is the
        fingertip's.
      base_xy: the arm's base, outside the table.
      link_lengths: the three link lengths (the last one ends at the fingertip).
      joint_lower, joint_upper: joint limits in radians, ``lower < upper``.
      action_length: norm of a joint move ``dq`` in radians.  0.12 moves the
        fingertip 0.099 +- 0.053 (mean +- std, median 0.088) per action over
        :func:`sample_arm_start` starts and random directions: the push task's
        0.1 on average (a joint move's fingertip displacement depends on the
        configuration and on the direction: ``dq`` along the redundant
        null-space direction barely moves the fingertip).
      start_range: sampled starts put the fingertip in the square
        ``disk +- start_range`` (the push task's start box; ``None``: anywhere).
      start_margin: sampled starts keep the fingertip more than
        ``contact_distance + start_margin`` from the disk centre.
    """

    push: PushConfig = PushConfig()
    base_xy: tuple[float, float] = (0.0, -1.0)
    link_lengths: tuple[float, float, float] = (0.9, 0.7, 0.4)
    joint_lower: tuple[float, float, float] = (0.0, -2.5, -2.5)
    joint_upper: tuple[float, float, float] = (math.pi, 2.5, 2.5)
    action_length: float = 0.12
    start_range: float | None = 1.0
    start_margin: float = 0.01

    def __post_init__(self) -> None:
        _check(isinstance(self.push, PushConfig),
               f"ArmConfig.push must be a PushConfig, got {type(self.push).__name__}")
        base = _floats(self.base_xy, 2, "base_xy")
        links = _floats(self.link_lengths, 3, "link_lengths")
        lower = _floats(self.joint_lower, 3, "joint_lower")
        upper = _floats(self.joint_upper, 3, "joint_upper")
        for name, value in (("base_xy", base), ("link_lengths", links), ("joint_lower", lower),
                            ("joint_upper", upper)):
            object.__setattr__(self, name, value)  # tuples of floats: hashable, comparable
        _check(all(length > 0 for length in links),
               f"ArmConfig.link_lengths must be > 0, got {links}")
        _check(all(lo < hi for lo, hi in zip(lower, upper)),
               f"ArmConfig.joint_lower must be < joint_upper per joint, got {lower} and {upper}")
        _check(max(abs(base[0]), abs(base[1])) > self.push.table_half_size,
               f"ArmConfig.base_xy={base} must lie outside the table "
               f"(half size {self.push.table_half_size})")
        _check(sum(links) > math.hypot(*base) + self.push.contact_distance,
               f"ArmConfig.link_lengths={links} (reach {sum(links):g}) cannot reach past the disk "
               f"from base_xy={base} (distance {math.hypot(*base):g} + contact distance "
               f"{self.push.contact_distance:g})")
        for name in ("action_length", "start_margin"):
            value = getattr(self, name)
            _check(isinstance(value, (int, float)) and not isinstance(value, bool)
                   and math.isfinite(value) and value > 0,
                   f"ArmConfig.{name} must be a finite number > 0, got {value!r}")
        _check(self.start_range is None or (
            isinstance(self.start_range, (int, float)) and not isinstance(self.start_range, bool)
            and self.start_range > self.push.contact_distance + self.start_margin),
            f"ArmConfig.start_range must be None or > contact distance + start_margin "
            f"({self.push.contact_distance + self.start_margin:g}), got {self.start_range!r}")

    @property
    def contact_distance(self) -> float:
        """Centre distance at which fingertip and disk touch."""
        return self.push.contact_distance


@struct.dataclass
class ArmState:
    """Joint angles ``q`` (float32 ``[..., 3]``) and the disk centre ``disk_xy``
    (float32 ``[..., 2]``); both at rest between pushes (quasistatic).  The agent's
    state ``s`` is ``q``."""

    q: jax.Array
    disk_xy: jax.Array


def _deep(config: ArmConfig) -> float:
    """Fingertip-disk centre distance at or below which a start is not simulated."""
    return config.contact_distance - 0.5 * config.push.finger_radius


def fingertip_xy(q: jax.Array, config: ArmConfig = ArmConfig()) -> jax.Array:
    """Forward kinematics ``[..., 3] -> [..., 2]``: the fingertip on the table, in ``q``'s
    float dtype (JAX or NumPy arrays)."""
    xp = np if isinstance(q, np.ndarray) else jnp
    lengths = xp.asarray(config.link_lengths, q.dtype)
    theta = xp.cumsum(q, axis=-1)
    tip = xp.stack([xp.sum(lengths * xp.cos(theta), -1), xp.sum(lengths * xp.sin(theta), -1)], -1)
    return tip + xp.asarray(config.base_xy, q.dtype)


def joint_path(q: jax.Array, dq: jax.Array, config: ArmConfig) -> jax.Array:
    """Joint angles ``[..., substeps, 3]`` at each physics substep of one move.

    ``dq`` is the (already normalised) move; the target ``q + dq`` is clipped to the
    joint limits, reached after ``move_substeps`` equal steps and held for
    ``settle_substeps``.  Works on NumPy (for the native reference) and JAX arrays.
    """
    xp = np if isinstance(q, np.ndarray) else jnp
    lo, hi = (xp.asarray(v, q.dtype) for v in (config.joint_lower, config.joint_upper))
    target = xp.clip(q + dq, lo, hi)
    n, total = config.push.move_substeps, config.push.substeps
    frac = xp.minimum(xp.arange(1, total + 1, dtype=q.dtype) / n, 1.0)
    return q[..., None, :] + frac[:, None] * (target - q)[..., None, :]


def _build_spec(config: ArmConfig) -> mujoco.MjSpec:
    xml = importlib.resources.files("lazyq_jax.tasks.arm").joinpath("assets", _SCENE).read_text()
    spec = mujoco.MjSpec.from_string(xml)
    spec.body("base").pos = [*config.base_xy, 0.0]
    for i, (name, length) in enumerate(zip(_LINKS, config.link_lengths)):
        spec.geom(name).fromto = [0.0, 0.0, 0.0, length, 0.0, 0.0]
        if i + 1 < len(_LINKS):
            spec.body(_LINKS[i + 1]).pos = [length, 0.0, 0.0]
    last = config.link_lengths[-1]
    drop = spec.site("tip").pos[2]
    spec.geom("rod").fromto = [last, 0.0, 0.0, last, 0.0, drop]
    spec.site("tip").pos = [last, 0.0, drop]
    for name, lo, hi in zip(ARM_JOINTS, config.joint_lower, config.joint_upper):
        spec.joint(name).range = [lo, hi]
    return spec


def load_arm_models(config: ArmConfig = ArmConfig()) -> tuple[mujoco.MjModel, mujoco.MjModel]:
    """``(full, physics)`` native models of the scene, set to ``config``.

    ``full`` has the arm on its hinge joints (``qpos = [disk_x, disk_y, q1, q2, q3]``):
    for rendering and the forward-kinematics check (site ``"tip"``).  ``physics``
    is the same scene without the arm's bodies (``qpos = qvel = [disk_x, disk_y]``,
    the fingertip is the only mocap body): the model :class:`ArmEnv` and
    :func:`native_arm_push` simulate.
    """
    spec = _build_spec(config)
    full = spec.compile()
    spec.delete(spec.body("base"))  # with the links, their joints and the site "tip"
    physics = spec.compile()
    for model in (full, physics):
        apply_push_config(model, config.push, finger_geom="fingertip")
    return full, physics


def arm_reward(disk_delta: jax.Array, goal_angle: jax.Array, config: ArmConfig = ArmConfig()
               ) -> jax.Array:
    """Eq. (15) with the push world's thresholds: :func:`push_reward` of the disk's move."""
    return push_reward(disk_delta, goal_angle, move_threshold=config.push.move_threshold,
                       cos_threshold=config.push.cos_threshold)


def sample_arm_start(key: jax.Array, config: ArmConfig = ArmConfig(),
                     extra: Callable[[jax.Array], jax.Array] | None = None,
                     disk_xy: jax.Array | None = None) -> jax.Array:
    """Joint angles ``[3]`` uniform in the joint limits, conditioned on a valid start.

    Valid: the fingertip is more than ``contact_distance + start_margin`` from the
    disk centre ``disk_xy`` (default the origin), inside ``disk +- start_range``
    (unless ``None``), and ``extra(q)`` (e.g. "behind the disk for a goal
    direction") holds.  Exact rejection sampling (:func:`rejection_sample`):
    vmappable, jittable; about half of the joint box is accepted by default.
    """
    lo = jnp.asarray(config.joint_lower, jnp.float32)
    hi = jnp.asarray(config.joint_upper, jnp.float32)
    disk = jnp.zeros(2, jnp.float32) if disk_xy is None else jnp.asarray(disk_xy, jnp.float32)
    min_dist = config.contact_distance + config.start_margin

    def propose(k):
        return jax.random.uniform(k, (3,), jnp.float32, lo, hi)

    def accept(q):
        rel = fingertip_xy(q, config) - disk
        ok = jnp.linalg.norm(rel) > min_dist
        if config.start_range is not None:
            ok &= jnp.max(jnp.abs(rel)) <= config.start_range
        return ok if extra is None else ok & extra(q)

    return rejection_sample(key, propose, accept)


class ArmEnv:
    """The arm scene as pure functions over :class:`ArmState` (vmap/jit them freely).

    >>> env = ArmEnv(ArmConfig())
    >>> state = env.reset(jnp.array([1.2, 0.9, 1.0]))        # disk at the origin
    >>> state, disk_delta = env.step(state, jnp.array([0.0, 0.0, 1.0]))

    Precision as :class:`lazyq_jax.tasks.push.env.PushEnv`: the physics runs in float64 when the
    env is built inside ``with jax.enable_x64(True)`` (and must then be traced
    there), in float32 otherwise; states and outputs are float32 either way.

    Attributes:
      config: the :class:`ArmConfig`.
      mj_model: the full native model, with the arm's joints (rendering, FK checks).
      physics_model: the native model that is simulated (no arm bodies).
      mjx_model: ``physics_model`` on the MJX JAX implementation.
      dtype: the physics precision.
    """

    def __init__(self, config: ArmConfig = ArmConfig()):
        if not isinstance(config, ArmConfig):
            raise TypeError(f"ArmEnv needs an ArmConfig, got {type(config).__name__}")
        self.config = config
        self.mj_model, self.physics_model = load_arm_models(config)
        device = jax.local_devices()[0]
        self.mjx_model = mjx.put_model(self.physics_model, device=device, impl="jax")
        self._data0 = mjx.make_data(self.mjx_model, device=device, impl="jax")
        # The disk's slide joints are all the physics model has: qpos = qvel = disk xy.
        assert self.physics_model.nq == self.physics_model.nv == 2
        assert self.physics_model.nmocap == 1 and self.physics_model.npair == 1
        self.dtype = jnp.float64 if _x64() else jnp.float32

    def fingertip(self, q: jax.Array) -> jax.Array:
        """Forward kinematics: fingertip ``[..., 2]`` of joint angles ``[..., 3]``."""
        return fingertip_xy(q, self.config)

    def reward(self, disk_delta: jax.Array, goal_angle: jax.Array) -> jax.Array:
        """Eq. (15) of the disk displacement (:func:`arm_reward`)."""
        return arm_reward(disk_delta, goal_angle, self.config)

    def reset(self, q: jax.Array, disk_xy: jax.Array | None = None) -> ArmState:
        """A state with joint angles ``q`` and the disk at ``disk_xy`` (default the origin).

        Outside ``jit`` raises ``ValueError`` for non-finite values, angles outside the
        joint limits, or a fingertip inside or touching the disk.  Under ``jit`` the
        angles are clipped to the limits; a fingertip deep inside the disk makes
        :meth:`step` a no-op (see the module docstring).
        """
        q = jnp.asarray(q, jnp.float32)
        disk = (jnp.zeros(q.shape[:-1] + (2,), jnp.float32) if disk_xy is None
                else jnp.asarray(disk_xy, jnp.float32))
        if q.shape[-1:] != (3,) or disk.shape[-1:] != (2,):
            raise ValueError(f"q and disk_xy must have shapes [..., 3] and [..., 2], got "
                             f"{q.shape} and {disk.shape}")
        lo = np.asarray(self.config.joint_lower, np.float32)
        hi = np.asarray(self.config.joint_upper, np.float32)
        if _is_concrete(q, disk):
            qn, dn = np.asarray(q), np.asarray(disk)
            if not (np.all(np.isfinite(qn)) and np.all(np.isfinite(dn))):
                raise ValueError("reset: q and disk_xy must be finite")
            if np.any(qn < lo) or np.any(qn > hi):
                raise ValueError(f"reset: q outside the joint limits [{lo}, {hi}]")
            dist = np.linalg.norm(fingertip_xy(qn, self.config) - dn, axis=-1)
            if np.any(dist <= self.config.contact_distance):
                raise ValueError(
                    f"reset: the fingertip starts inside or touching the disk (centre distance "
                    f"{float(np.min(dist)):.4f} <= {self.config.contact_distance}); sample "
                    "starts with sample_arm_start")
            return ArmState(q, disk)
        return ArmState(jnp.clip(q, lo, hi), disk)

    def step(self, state: ArmState, dq: jax.Array) -> tuple[ArmState, jax.Array]:
        """One quasistatic push: the joints move by ``dq`` rescaled to ``action_length``
        (target clipped to the limits).

        Returns the next state and the disk displacement (Eq. 15's input).
        Non-finite moves raise outside ``jit`` and are no-ops inside it
        (:func:`normalize_action`).  Unbatched; use ``jax.vmap`` for batches.
        """
        if (self.dtype == jnp.float64) != _x64():
            raise RuntimeError(
                f"this ArmEnv simulates in {jnp.dtype(self.dtype).name} but is traced with "
                f"jax_enable_x64={_x64()}; build and call it in the same precision (e.g. both "
                "inside `with jax.enable_x64(True):`)")
        if _is_concrete(dq) and not np.all(np.isfinite(np.asarray(dq))):
            raise ValueError(f"step: dq must be finite, got {np.asarray(dq)}")
        cfg, dtype = self.config, self.dtype
        dq = normalize_action(dq, cfg.action_length)
        q0 = state.q.astype(dtype)
        path = joint_path(q0, dq.astype(dtype), cfg)
        tips = fingertip_xy(path, cfg)
        data = self._data0.replace(qpos=state.disk_xy.astype(dtype))
        coulomb = cfg.push.friction == "coulomb"

        def substep(data, tip):
            model = self.mjx_model
            data = data.replace(mocap_pos=jnp.concatenate([tip, jnp.zeros(1, dtype)])[None])
            if coulomb:  # this substep's linearisation, exactly as PushEnv.step
                damping, force = coulomb_friction(data.qvel, cfg.push)
                model = model.replace(dof_damping=damping)
                data = data.replace(qfrc_applied=force)
            return mjx.step(model, data), None

        data, _ = jax.lax.scan(substep, data, tips)
        disk = data.qpos.astype(jnp.float32)
        # A start deep inside the disk is not simulated (module docstring).
        valid = jnp.linalg.norm(fingertip_xy(q0, cfg) - state.disk_xy.astype(dtype)) > _deep(cfg)
        q1 = jnp.where(valid, path[-1].astype(jnp.float32), state.q)
        disk = jnp.where(valid, disk, state.disk_xy)
        return ArmState(q1, disk), disk - state.disk_xy


def native_arm_push(env: ArmEnv, q: np.ndarray, disk_xy: np.ndarray, dq: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Final ``(q [B, 3], disk [B, 2])`` of a batch of arm pushes in native MuJoCo (float64).

    The reference for :meth:`ArmEnv.step`: one push after another in a Python loop.
    The fingertip path is computed independently of the JAX forward kinematics:
    the full model's joints are set to each interpolated configuration and
    ``mj_kinematics`` gives the site ``"tip"``; the mocap fingertip of the physics
    model goes there, the ``"coulomb"`` friction is linearised (as in MJX), and
    ``mj_step`` runs.  Starts deep inside the disk are no-ops, as in :meth:`ArmEnv.step`.
    """
    cfg = env.config
    q = np.asarray(q, np.float32).reshape(-1, 3).astype(np.float64)
    disk = np.asarray(disk_xy, np.float32).reshape(-1, 2).astype(np.float64)
    step = np.asarray(normalize_action(np.asarray(dq, np.float32), cfg.action_length),
                      np.float64).reshape(-1, 3)
    full, model = env.mj_model, copy.copy(env.physics_model)
    fdata, data = mujoco.MjData(full), mujoco.MjData(model)
    arm_qpos = np.array([full.jnt_qposadr[mujoco.mj_name2id(full, mujoco.mjtObj.mjOBJ_JOINT, n)]
                         for n in ARM_JOINTS])
    tip_site = mujoco.mj_name2id(full, mujoco.mjtObj.mjOBJ_SITE, "tip")
    out_q, out_disk = q.copy(), disk.copy()
    for b in range(q.shape[0]):
        fdata.qpos[arm_qpos] = q[b]
        mujoco.mj_kinematics(full, fdata)
        if np.linalg.norm(fdata.site_xpos[tip_site, :2] - disk[b]) <= _deep(cfg):
            continue
        mujoco.mj_resetData(model, data)
        data.qpos[:] = disk[b]
        path = joint_path(q[b], step[b], cfg)
        for qk in path:
            fdata.qpos[arm_qpos] = qk
            mujoco.mj_kinematics(full, fdata)
            data.mocap_pos[0] = fdata.site_xpos[tip_site]
            if cfg.push.friction == "coulomb":
                damping, force = coulomb_friction(data.qvel.copy(), cfg.push)
                model.dof_damping[:] = damping
                data.qfrc_applied[:] = force
            mujoco.mj_step(model, data)
        out_q[b], out_disk[b] = path[-1], data.qpos
    return out_q, out_disk
