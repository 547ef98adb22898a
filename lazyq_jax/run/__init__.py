"""One runner for every task, agent and data source (:mod:`lazyq_jax.run.runner`)."""

from lazyq_jax.run.rundir import RunDirError, parse_method
from lazyq_jax.run.runner import evaluate_run, load_policy, run

__all__ = ["RunDirError", "evaluate_run", "load_policy", "parse_method", "run"]
