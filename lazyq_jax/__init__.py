"""lazyq-jax: lazy action value models for Q-learning (Schubert & Toussaint, 2020) in JAX.

The public API, re-exported here (see the README's API tour):

* the lazy core (§IV, §V-A-2), for any states, actions and goals:
  :func:`find_neighbours`, :func:`fit_local_linear`, :func:`greedy_action` (Eq. 9),
  :func:`lazy_target` (Eq. 7/8), :func:`dataset_targets` (Eq. 11-14), :class:`Transitions`
* learning (§IV-E): :func:`make_train`, :func:`save_checkpoint` (:func:`checkpoint_writer` for
  a checkpoint per block), :func:`load_checkpoint`
* acting: :func:`make_lazy_policy`, :func:`lazy_policy`
* agents (lazy Q and the baselines, one file each): :func:`lazyq_jax.agents.make`
* tasks (the push world of §V-A-1, the arm; one folder each): :func:`lazyq_jax.tasks.get`,
  :func:`preset`, :class:`PushEnv`, :func:`push_reward` (Eq. 15), :class:`ArmEnv`
* one runner for every task, agent and data source: :func:`run`, :func:`evaluate_run`,
  :func:`load_policy` (the trained policy of any run directory)
* evidence: :func:`t_interval` (mean and 95 % CI over seeds)
* devices: :func:`make_mesh` (pass ``mesh=`` to the collection, search and training)
"""

from lazyq_jax import agents, tasks
from lazyq_jax.agents import Agent, Problem, Spec
from lazyq_jax.checkpoint import (CheckpointDamaged, CheckpointError, checkpoint_writer,
                                  load_checkpoint, load_latest_intact, save_checkpoint)
from lazyq_jax.config import (Config, ConfigError, NeighbourConfig, OnlineConfig, ParallelConfig,
                              TrainConfig, override)
from lazyq_jax.data import DatasetError, load_dataset, save_dataset
from lazyq_jax.local_model import (apply_projection, expectile, fit_local_linear, fit_with_offsets,
                                   greedy_action, max_linear, precompute_projection, safe_norm)
from lazyq_jax.neighbours import (GridIndex, Neighbours, build_index, check_found, find_neighbours,
                                  query_neighbours, search_all)
from lazyq_jax.networks import ValueNetwork
from lazyq_jax.parallel import make_mesh
from lazyq_jax.policy import LazyPolicy, lazy_policy, make_lazy_policy
from lazyq_jax.run import RunDirError, evaluate_run, load_policy, load_run, run
from lazyq_jax.stats import t_interval
from lazyq_jax.targets import (TargetDiagnostics, bootstrap_table, bootstrap_values, dataset_targets,
                               double_dqn_target, evaluate_in_batches, in_sample_target, lazy_target,
                               local_fits)
from lazyq_jax.tasks import preset
from lazyq_jax.tasks.arm import ArmConfig, ArmEnv, collect_arm
from lazyq_jax.tasks.push import (FORGIVING_PUSH, CollectConfig, EvalConfig, PushConfig, PushEnv,
                                  PushState, push_reward)
from lazyq_jax.tasks.push.collect import collect, dataset_summary
from lazyq_jax.train import TrainState, make_train
from lazyq_jax.types import Transitions, pad_transitions

__version__ = "0.3.0"  # pyproject.toml says the same (tests/test_readme.py)

__all__ = [
    "Agent", "ArmConfig", "ArmEnv", "CheckpointDamaged", "CheckpointError", "CollectConfig", "Config",
    "ConfigError", "DatasetError", "EvalConfig", "FORGIVING_PUSH", "GridIndex", "LazyPolicy",
    "NeighbourConfig", "Neighbours", "OnlineConfig", "ParallelConfig", "Problem", "PushConfig",
    "PushEnv", "PushState", "RunDirError", "Spec", "TargetDiagnostics", "TrainConfig", "TrainState",
    "Transitions", "ValueNetwork", "agents", "apply_projection", "bootstrap_table",
    "bootstrap_values", "build_index", "check_found", "checkpoint_writer", "collect", "collect_arm",
    "dataset_summary",
    "dataset_targets", "double_dqn_target", "evaluate_in_batches", "evaluate_run",
    "expectile", "find_neighbours", "fit_local_linear", "fit_with_offsets", "greedy_action",
    "in_sample_target", "lazy_policy", "lazy_target",
    "load_checkpoint", "load_dataset", "load_latest_intact", "load_policy", "load_run", "local_fits",
    "make_lazy_policy", "make_mesh", "make_train", "max_linear", "override", "pad_transitions",
    "precompute_projection", "preset", "push_reward", "query_neighbours", "run", "safe_norm",
    "save_checkpoint", "save_dataset", "search_all", "t_interval", "tasks",
]
