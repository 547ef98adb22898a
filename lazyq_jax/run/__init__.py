"""One runner for every task, agent and data source (:mod:`lazyq_jax.run.runner`)."""

from lazyq_jax.run import report
from lazyq_jax.run.rundir import RunDirError, locked, parse_method
from lazyq_jax.run.runner import LoadedRun, evaluate_run, load_policy, load_run, run

__all__ = ["LoadedRun", "RunDirError", "evaluate_run", "load_policy", "load_run", "locked", "parse_method",
           "report", "run"]
