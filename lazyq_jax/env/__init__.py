"""The pushing task: MJX scene, reward (Eq. 15), start samplers, native cross-check."""

from lazyq_jax.env.push import PushEnv, PushState, finger_path, load_mj_model, normalize_action
from lazyq_jax.env.reward import disk_moved, push_reward
from lazyq_jax.env.sampling import rejection_sample, sample_outside_disk

__all__ = ["PushEnv", "PushState", "disk_moved", "finger_path", "load_mj_model",
           "normalize_action", "push_reward", "rejection_sample", "sample_outside_disk"]
