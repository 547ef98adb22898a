"""The finger-pushes-disk scene (paper §V-A-1) as a pure, vmappable MJX environment."""

from __future__ import annotations

import contextlib
import importlib.resources
import io

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct

# MJX prints "Failed to import warp" to stdout when the optional warp backend is
# absent; we use the JAX implementation, so keep that out of parsed outputs.
with contextlib.redirect_stdout(io.StringIO()):
    from mujoco import mjx

from lazyq_jax.tasks.push.config import PushConfig

_SCENE = "push.xml"


@struct.dataclass
class PushState:
    """Where the finger and the disk are; both are at rest between pushes (quasistatic).

    ``finger_xy`` and ``disk_xy`` are float32 ``[..., 2]`` table coordinates.
    """

    finger_xy: jax.Array
    disk_xy: jax.Array

    @property
    def relative(self) -> jax.Array:
        """The agent's state ``s``: finger position relative to the disk centre."""
        return self.finger_xy - self.disk_xy


def load_mj_model(config: PushConfig = PushConfig()) -> mujoco.MjModel:
    """The native MuJoCo model of the scene shipped in the package, set to ``config``."""
    xml = importlib.resources.files("lazyq_jax.tasks.push").joinpath("assets", _SCENE).read_text()
    model = mujoco.MjModel.from_xml_string(xml)
    apply_push_config(model, config)
    return model


def apply_push_config(model: mujoco.MjModel, config: PushConfig, finger_geom: str = "finger") -> None:
    """Set the disk world of ``config`` on a native model holding the disk, the table and a
    finger geom named ``finger_geom`` (the push scene, or the arm's with its fingertip)."""
    geom = lambda name: mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, name)
    joint = lambda name: model.jnt_dofadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)]
    model.geom_size[geom("disk"), 0] = config.disk_radius
    model.geom_size[geom(finger_geom), 0] = config.finger_radius
    model.geom_size[geom("table"), :2] = config.table_half_size
    body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "disk")
    # Scaling mass and inertia together keeps the drag's equivalent box (its size is
    # sqrt(6 I / m)) and so the anisotropic term independent of the mass.
    scale = config.disk_mass / model.body_mass[body]
    model.body_mass[body] *= scale
    model.body_inertia[body] *= scale
    model.dof_damping[joint("disk_x")] = config.damping
    model.dof_damping[joint("disk_y")] = config.damping
    # "fluid": MuJoCo's quadratic drag; "coulomb": set per substep by PushEnv.step.
    model.opt.density = config.anisotropy if config.friction == "fluid" else 0.0
    model.pair_solref[0] = (config.contact_timeconst, config.contact_dampratio)
    model.opt.timestep = config.timestep
    model.opt.iterations = config.solver_iterations
    model.opt.ls_iterations = config.ls_iterations


def coulomb_friction(qvel, config: PushConfig):
    """The ``"coulomb"`` friction of the disk per slide joint (x, y), linearised at ``qvel``.

    ``F(v) = -mu v / sqrt(v^2 + eps^2) - damping v`` with ``mu = friction_coefficient``
    and ``eps = friction_smoothing``: Coulomb friction per table axis (smoothed below
    speed ``eps``) plus viscous damping.  Returns ``(damping, force)``
    with ``damping = -dF/dv`` (MuJoCo's Euler integrator treats joint damping
    implicitly) and ``force = F(v) + (damping - config.damping) v`` (applied
    explicitly), so that one step integrates ``F(v_new) ~ F(v) + F'(v) (v_new - v)``:
    stable for any ``mu / eps``.  Works on NumPy and JAX arrays.
    """
    mu, eps = config.friction_coefficient, config.friction_smoothing
    q = qvel * qvel + eps * eps
    root = q ** 0.5
    tangent = mu * eps * eps / (q * root)
    return config.damping + tangent, -mu * qvel * qvel * qvel / (q * root)


def finger_path(start_xy: jax.Array, action: jax.Array, config: PushConfig) -> jax.Array:
    """Finger positions ``[substeps, 2]`` at each physics substep of one quasistatic move.

    The finger advances ``action / move_substeps`` per substep, then holds for
    ``settle_substeps``.  MJX and native MuJoCo both follow this path.
    """
    n = config.move_substeps
    frac = jnp.minimum(jnp.arange(1, config.substeps + 1, dtype=start_xy.dtype) / n, 1.0)
    return start_xy[..., None, :] + frac[:, None] * action[..., None, :]


def normalize_action(action: jax.Array, action_length: float) -> jax.Array:
    """Rescale a move to length ``action_length`` (the action set is that circle).

    A zero vector, or one with a NaN/inf entry, becomes the zero move (the finger
    stays where it is): inside ``jit`` a bad action cannot raise, so it does nothing.
    :meth:`PushEnv.step` raises for non-finite actions when called outside ``jit``.
    """
    action = jnp.asarray(action, jnp.float32)
    norm = jnp.linalg.norm(jnp.where(jnp.isfinite(action), action, 0.0), axis=-1, keepdims=True)
    ok = jnp.all(jnp.isfinite(action), axis=-1, keepdims=True) & (norm > 0)
    return jnp.where(ok, action * (action_length / jnp.where(ok, norm, 1.0)), 0.0)


def _x64() -> bool:
    return bool(jax.config.jax_enable_x64)


def _is_concrete(*xs) -> bool:
    return not any(isinstance(x, jax.core.Tracer) for x in xs)


class PushEnv:
    """The pushing scene as pure functions over :class:`PushState` (vmap/jit them freely).

    >>> env = PushEnv(PushConfig())
    >>> state = env.reset(jnp.array([-0.4, 0.0]))            # disk at the origin
    >>> state, disk_delta = env.step(state, jnp.array([1.0, 0.0]))

    The physics runs in the precision JAX is in when the env is built (float64
    inside ``with jax.enable_x64(True)``, as :func:`lazyq_jax.collect` does; float32
    otherwise) and must be traced in that same precision.  States and outputs are
    float32 either way.

    Attributes:
      config: the :class:`PushConfig`.
      mj_model: the native ``mujoco.MjModel`` (for ``mujoco.rollout`` or a viewer).
      mjx_model: the same model on the MJX JAX implementation.
      dtype: the physics precision, ``jnp.float32`` or ``jnp.float64``.
    """

    def __init__(self, config: PushConfig = PushConfig()):
        if not isinstance(config, PushConfig):
            raise TypeError(f"PushEnv needs a PushConfig, got {type(config).__name__}")
        self.config = config
        self.mj_model = load_mj_model(config)
        # The JAX implementation, explicitly: runs on CPU and GPU without warp.
        # On this process's first device: with several processes, jax.devices()[0] may
        # belong to another one.
        device = jax.local_devices()[0]
        self.mjx_model = mjx.put_model(self.mj_model, device=device, impl="jax")
        self._data0 = mjx.make_data(self.mjx_model, device=device, impl="jax")
        self.dtype = jnp.float64 if _x64() else jnp.float32

    def reset(self, finger_xy: jax.Array, disk_xy: jax.Array | None = None) -> PushState:
        """A state with the finger at ``finger_xy`` and the disk at ``disk_xy`` (default origin).

        A finger inside or touching the disk is never simulated: outside ``jit`` it
        raises ``ValueError``; under ``jit`` (where raising is impossible) the finger
        is moved radially outward to touching distance plus 1e-4.  Samplers in
        :mod:`lazyq_jax.tasks.sampling` only produce valid starts.
        """
        finger = jnp.asarray(finger_xy, jnp.float32)
        disk = jnp.zeros_like(finger) if disk_xy is None else jnp.asarray(disk_xy, jnp.float32)
        if finger.shape[-1:] != (2,) or disk.shape[-1:] != (2,):
            raise ValueError(f"finger_xy and disk_xy must have shape [..., 2], got "
                             f"{finger.shape} and {disk.shape}")
        min_dist = self.config.contact_distance
        if _is_concrete(finger, disk):
            f, d = np.asarray(finger), np.asarray(disk)
            if not (np.all(np.isfinite(f)) and np.all(np.isfinite(d))):
                raise ValueError("reset: finger_xy and disk_xy must be finite")
            dist = np.linalg.norm(f - d, axis=-1)
            if np.any(dist <= min_dist):
                raise ValueError(
                    f"reset: the finger starts inside or touching the disk (centre distance "
                    f"{float(np.min(dist)):.4f} <= {min_dist}); sample starts with "
                    "lazyq_jax.tasks.sampling.sample_outside_disk")
            return PushState(finger, disk)
        rel = finger - disk
        dist = jnp.linalg.norm(rel, axis=-1, keepdims=True)
        safe = jnp.where(dist > 0, rel / jnp.where(dist > 0, dist, 1.0), jnp.array([1.0, 0.0]))
        pushed_out = disk + safe * (min_dist + 1e-4)
        return PushState(jnp.where(dist > min_dist, finger, pushed_out).astype(jnp.float32), disk)

    def step(self, state: PushState, action: jax.Array) -> tuple[PushState, jax.Array]:
        """One quasistatic push: the finger moves by ``action`` rescaled to ``action_length``.

        Returns the next state and the disk displacement ``delta_disk`` (Eq. 15's input).
        Non-finite actions raise ``ValueError`` outside ``jit`` and are no-ops inside it
        (see :func:`normalize_action`).  Unbatched; use ``jax.vmap`` for batches.
        """
        if (self.dtype == jnp.float64) != _x64():
            raise RuntimeError(
                f"this PushEnv simulates in {jnp.dtype(self.dtype).name} but is traced with "
                f"jax_enable_x64={_x64()}; build and call it in the same precision (e.g. both "
                "inside `with jax.enable_x64(True):`)")
        if _is_concrete(action) and not np.all(np.isfinite(np.asarray(action))):
            raise ValueError(f"step: action must be finite, got {np.asarray(action)}")
        dtype = self.dtype
        action = normalize_action(action, self.config.action_length)
        path = finger_path(state.finger_xy.astype(dtype), action.astype(dtype), self.config)
        data = self._data0.replace(qpos=state.disk_xy.astype(dtype))
        coulomb = self.config.friction == "coulomb"

        def substep(data, finger_xy):
            model = self.mjx_model
            data = data.replace(mocap_pos=jnp.concatenate([finger_xy, jnp.zeros(1, dtype)])[None])
            if coulomb:  # this substep's linearisation (see coulomb_friction)
                damping, force = coulomb_friction(data.qvel, self.config)
                model = model.replace(dof_damping=damping)
                data = data.replace(qfrc_applied=force)
            return mjx.step(model, data), None

        data, _ = jax.lax.scan(substep, data, path)
        disk = data.qpos[:2].astype(jnp.float32)
        return PushState(path[-1].astype(jnp.float32), disk), disk - state.disk_xy
