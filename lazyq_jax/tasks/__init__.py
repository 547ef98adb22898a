"""The task registry: ``name -> Task`` (:class:`lazyq_jax.tasks.base.Task`).

A new task is one folder beside ``push/`` and ``arm/`` with a :class:`Task` subclass, and
one line in :data:`TASKS` below (see docs/design.md, "Adding a task").
"""

from __future__ import annotations

from lazyq_jax.config import Config, ConfigError, from_dict
from lazyq_jax.tasks.arm import ArmTask
from lazyq_jax.tasks.base import Task
from lazyq_jax.tasks.cube import CubeTask
from lazyq_jax.tasks.pointmaze import DATASETS as POINTMAZE_DATASETS, PointMazeTask
from lazyq_jax.tasks.push import PushTask

TASKS: dict[str, Task] = {
    "push": PushTask(),
    "arm": ArmTask("arm", disk_range=None),
    "arm-long": ArmTask("arm-long", disk_range=0.3, start_range=0.6),
    "pointmaze": PointMazeTask(name="pointmaze"),  # pointmaze-medium-navigate, by its old name
    **{name: PointMazeTask(*name.split("-")[1:]) for name in POINTMAZE_DATASETS},
    "cube-single-play": CubeTask(),
}

#: benchmark suites (``python -m lazyq_jax benchmark SUITE``): name -> its datasets' tasks
SUITES: dict[str, tuple[str, ...]] = {"ogbench-pointmaze": POINTMAZE_DATASETS}


def canonical(name: str) -> str:
    """``name`` as registered: OGBench's dataset ids are accepted with their version
    (``pointmaze-large-stitch-v0`` is ``pointmaze-large-stitch``)."""
    return name[:-3] if name.endswith("-v0") and name[:-3] in TASKS else name


def get(name: str) -> Task:
    """The task called ``name`` (:class:`ConfigError` listing the known ones otherwise)."""
    name = canonical(name)
    if name not in TASKS:
        raise ConfigError(f"unknown task {name!r}; known tasks: {', '.join(TASKS)}")
    return TASKS[name]


def preset(task: str = "push", name: str = "paper") -> Config:
    """The run config of ``task``'s preset ``name`` (``paper`` is every task's default)."""
    presets = get(task).presets
    if name not in presets:
        raise ConfigError(f"task {task!r} has no preset {name!r}; its presets: {', '.join(presets)}")
    return presets[name]


def config_from_dict(data: dict) -> Config:
    """A :class:`Config` from its JSON form (the task's sections by the task's classes)."""
    if not isinstance(data, dict) or "task" not in data:
        raise ConfigError("a stored config must be a dict with a 'task' field")
    task = get(data["task"])
    return from_dict(Config, data, sections={"collect": task.collect_config, "eval": task.eval_config})


__all__ = ["SUITES", "TASKS", "Task", "canonical", "config_from_dict", "get", "preset"]
