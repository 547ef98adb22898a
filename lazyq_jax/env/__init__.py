"""The tasks' physics: the finger pushing the disk (MJX scene, reward Eq. 15, start samplers,
native cross-check, a scripted controller) and a planar 3-link arm pushing it in joint space."""

from lazyq_jax.env.push import PushEnv, PushState, finger_path, load_mj_model, normalize_action
from lazyq_jax.env.reward import disk_moved, push_reward
from lazyq_jax.env.sampling import rejection_sample, sample_outside_disk
from lazyq_jax.env.arm import ArmConfig, ArmEnv, ArmState, fingertip_xy, sample_arm_start

__all__ = ["ArmConfig", "ArmEnv", "ArmState", "fingertip_xy", "sample_arm_start", "PushEnv", "PushState", "disk_moved", "finger_path", "load_mj_model",
           "normalize_action", "push_reward", "rejection_sample", "sample_outside_disk"]
