"""lazyq-jax: lazy action value models for Q-learning (Schubert & Toussaint, 2020) in JAX.

The public API, re-exported here (see the README's API tour):

* push world (§V-A-1): :class:`PushEnv`, :class:`PushState`, :func:`push_reward` (Eq. 15)
* data (§V-A-3): :func:`collect`, :func:`save_dataset`, :func:`load_dataset`, :class:`Transitions`
* lazy core (§IV, §V-A-2): :func:`find_neighbours`, :func:`fit_local_linear`,
  :func:`greedy_action` (Eq. 9), :func:`lazy_target` (Eq. 7/8), :func:`dataset_targets` (Eq. 11-14)
* learning (§IV-E): :func:`make_train`, :func:`save_checkpoint`, :func:`load_checkpoint`
* acting (§V-B): :func:`make_lazy_policy`, :func:`lazy_policy`, :func:`evaluate_run`
* devices: :func:`make_mesh` (pass ``mesh=`` to ``collect``, ``find_neighbours``, ``make_train``)
* evidence: :func:`run_study` (many seeds in one program per phase), :func:`t_interval`
  (mean and 95 % CI over seeds), :func:`evaluate_stacked`, :func:`pad_transitions`
"""

from lazyq_jax.checkpoint import (CheckpointDamaged, CheckpointError, load_checkpoint,
                                  load_latest_intact, save_checkpoint)
from lazyq_jax.config import (FORGIVING_PUSH, CollectConfig, Config, ConfigError, EvalConfig,
                              NeighbourConfig, ParallelConfig, PushConfig, TrainConfig, override,
                              preset)
from lazyq_jax.data import DatasetError, collect, dataset_summary, load_dataset, save_dataset
from lazyq_jax.env import PushEnv, PushState, push_reward
from lazyq_jax.evaluate import evaluate_run, evaluate_stacked, protocol_a, protocol_b
from lazyq_jax.local_model import (apply_projection, fit_local_linear, greedy_action,
                                   precompute_projection, safe_norm)
from lazyq_jax.neighbours import (GridIndex, Neighbours, build_index, check_found, find_neighbours,
                                  query_neighbours, search_all)
from lazyq_jax.networks import ValueNetwork
from lazyq_jax.parallel import make_mesh
from lazyq_jax.pipeline import fit
from lazyq_jax.policy import LazyPolicy, lazy_policy, make_lazy_policy
from lazyq_jax.targets import (TargetDiagnostics, bootstrap_table, bootstrap_values, dataset_targets,
                               double_dqn_target, evaluate_in_batches, lazy_target, local_fits)
from lazyq_jax.train import TrainState, make_train, make_train_for
from lazyq_jax.stats import t_interval
from lazyq_jax.study import run_study
from lazyq_jax.types import Transitions, pad_transitions

__version__ = "0.1.0"

__all__ = [
    "CheckpointDamaged", "CheckpointError", "FORGIVING_PUSH", "evaluate_stacked", "load_latest_intact",
    "pad_transitions", "run_study", "t_interval", "CollectConfig", "Config", "ConfigError", "DatasetError", "EvalConfig",
    "GridIndex", "LazyPolicy", "NeighbourConfig", "Neighbours", "ParallelConfig", "PushConfig", "PushEnv",
    "PushState", "TargetDiagnostics", "TrainConfig", "TrainState", "Transitions", "ValueNetwork",
    "apply_projection", "bootstrap_table", "bootstrap_values", "build_index", "check_found", "collect",
    "dataset_summary", "dataset_targets", "double_dqn_target", "local_fits", "evaluate_in_batches", "evaluate_run", "find_neighbours",
    "fit", "fit_local_linear", "greedy_action", "lazy_policy", "lazy_target", "load_checkpoint",
    "load_dataset", "make_lazy_policy", "make_mesh", "make_train", "make_train_for", "override", "precompute_projection",
    "preset", "protocol_a", "protocol_b", "push_reward", "query_neighbours", "safe_norm",
    "save_checkpoint", "save_dataset", "search_all",
]
