"""A run directory: its layout, its lock and guard against mixing runs, and the method specs.

Layout (one seed or many, one method or many: a single run is a study of one seed)::

    run.json                      task, config, seeds (a resume must match them)
    data/<seed>/dataset.npz       each seed's static dataset (+ summary.json);
    data/<seed>/round_<r>.npz     the moves online round r added (online runs)
    <method>/method.json          the agent, its config and budget (a resume must match)
    <method>/checkpoints/<block>/ the seeds' training states, stacked (orbax)
    <method>/metrics.jsonl        per block: every metric as a list over the seeds
    <method>/rounds.jsonl         online runs: per round, moves, pushes, a quick protocol A
    <method>/eval.json            per seed: the task's evaluation
    <method>/timings.json         seconds per phase
    results.json, summary.md      per seed and mean with 95 % CI (:mod:`lazyq_jax.stats`)
    figures/                      comparisons; figures/<method>/: the task's figures and a GIF
    .lock                         who holds the directory (:func:`locked`)
"""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import json
import os
import re
import shutil
import socket
import sys
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from lazyq_jax.agents import METHODS
from lazyq_jax.config import Config, ConfigError, to_dict
from lazyq_jax.parallel import barrier, is_main_process

RUN_VERSION = 2  # 2: one runner for every task, agent and data source


class RunDirError(ValueError):
    """The run directory holds another run that this call would mix with or overwrite."""


def write_json(path: Path, data: Any, indent: int | None = 1) -> None:
    """Write JSON (process 0 only; the others return), atomically: a temporary file renamed
    into place, so that another process reading it (a multi-host run shares the directory)
    sees the old or the new file, never a half-written one."""
    if is_main_process():
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text(json.dumps(data, indent=indent))
        os.replace(tmp, path)


def as_json(data: Any) -> Any:
    """``data`` as JSON gives it back (tuples become lists): what stored records compare to."""
    return json.loads(json.dumps(data))


def append_jsonl(path: Path, record: dict) -> None:
    if is_main_process():
        with path.open("a") as f:
            f.write(json.dumps(record) + "\n")


def read_jsonl(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines() if line] if path.exists() else []


def keep_jsonl(path: Path, keep) -> None:
    """Keep the lines of ``path`` whose record ``keep(record)`` accepts (e.g. on resume)."""
    if is_main_process() and path.exists():
        path.write_text("".join(json.dumps(r) + "\n" for r in read_jsonl(path) if keep(r)))


# ----------------------------------------------------------------------------- methods


@dataclasses.dataclass(frozen=True)
class MethodSpec:
    """``"iql:temperature=10:budget=4"``: an agent name, overrides of its config fields
    and (baselines) ``budget``, a multiple of lazy Q's gradient steps."""

    text: str
    name: str
    options: tuple[tuple[str, str], ...]

    @property
    def dirname(self) -> str:
        return re.sub(r"[^A-Za-z0-9_.=-]", "_", self.text.replace(":", "_"))


def parse_method(text: str) -> MethodSpec:
    name, *parts = text.strip().split(":")
    if name not in METHODS:
        raise ConfigError(f"unknown method {name!r} in {text!r}; known methods: {', '.join(METHODS)}")
    options = []
    for part in parts:
        if "=" not in part:
            raise ConfigError(f"method option {part!r} in {text!r} must look like field=value")
        key, value = part.split("=", 1)
        options.append((key.strip(), value.strip()))
    if options and name in ("lazy", "random", "scripted"):
        raise ConfigError(f"{text!r}: {name} takes no options (set lazy Q's with --set)")
    return MethodSpec(text.strip(), name, tuple(options))


def check_methods(methods: Sequence[str]) -> tuple[MethodSpec, ...]:
    specs = tuple(parse_method(m) for m in methods if m.strip())
    if not specs:
        raise ConfigError(f"a run needs at least one method; choose from {', '.join(METHODS)}")
    if len({s.text for s in specs}) != len(specs):
        raise ConfigError(f"methods must be distinct, got {[s.text for s in specs]}")
    return specs


def check_seeds(seeds: Sequence[int]) -> tuple[int, ...]:
    seeds = tuple(seeds)
    if not seeds:
        raise ConfigError("a run needs at least one seed (--seeds N)")
    if any(not isinstance(s, (int, np.integer)) or isinstance(s, bool) or s < 0 for s in seeds):
        raise ConfigError(f"seeds must be integers >= 0, got {list(seeds)}")
    if len(set(seeds)) != len(seeds):
        raise ConfigError(f"seeds must be distinct, got {list(seeds)}")
    return tuple(int(s) for s in seeds)


# ----------------------------------------------------------------------------- the lock and the guard

LOCK = ".lock"


def _holder(f) -> str:
    """Who holds the lock whose file ``f`` is, as its holder wrote it (it may still be
    writing: a few tries)."""
    for _ in range(20):
        f.seek(0)
        try:
            h = json.loads(f.read())
            return f"process {h['pid']} on {h['host']} (started {h['started']}: {h['command']})"
        except (ValueError, KeyError, TypeError):
            time.sleep(0.05)
    return "another process (it has not written its name yet)"


@contextlib.contextmanager
def locked(run_dir: Path):
    """Hold ``run_dir`` for this process while the block runs: a second process (``train``,
    ``study``, ``evaluate``, ``plot``, ``collect``) on it is refused at once with a
    :class:`RunDirError` naming the holder (pid, host, start, command line).

    An exclusive ``fcntl.flock`` on ``run_dir/.lock``: the kernel releases it when the
    holder ends, however it ends (``kill -9`` included), so a dead holder's lock is taken
    over and its run resumes.  Two processes starting at once: one gets it.  Only JAX
    process 0 takes it (the others write nothing); the directory is created if missing.
    """
    if not is_main_process():
        yield
        return
    run_dir.mkdir(parents=True, exist_ok=True)
    with open(run_dir / LOCK, "a+") as f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise RunDirError(f"{run_dir} is in use by {_holder(f)}; wait for it to end (or stop "
                              "it), or pick another --run-dir") from None
        f.seek(0)
        f.truncate()
        f.write(json.dumps({"pid": os.getpid(), "host": socket.gethostname(), "command": " ".join(sys.orig_argv),
                            "started": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime())}))
        f.flush()
        yield


def config_diff(a: Any, b: Any, prefix: str = "") -> list[str]:
    """The dotted names of the fields where two config dicts differ."""
    if isinstance(a, dict) and isinstance(b, dict):
        return [d for key in sorted(set(a) | set(b))
                for d in config_diff(a.get(key), b.get(key), f"{prefix}{key}.")]
    return [] if a == b else [prefix.rstrip(".")]


def lookup(tree: Any, dotted: str) -> tuple[bool, Any]:
    """``(found, value)`` of the dotted field ``dotted`` in a nested dict."""
    for part in dotted.split("."):
        if not isinstance(tree, dict) or part not in tree:
            return False, None
        tree = tree[part]
    return True, tree


def _added_at_default(stored: dict, record: dict, defaults: dict, dotted: str) -> bool:
    """Whether ``dotted`` is a field the stored record lacks (added to lazyq-jax after it was
    made) and ``record`` holds at its default (``defaults``): it was made with what the
    default does."""
    return not lookup(stored, dotted)[0] and lookup(defaults, dotted) == lookup(record, dotted)


def field_defaults(config: Any) -> dict:
    """The defaults of a (nested) config dataclass's fields, as JSON (sections by their
    current value's class)."""
    out = {}
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if dataclasses.is_dataclass(value):
            out[f.name] = field_defaults(value)
        elif f.default is not dataclasses.MISSING:
            out[f.name] = f.default
    return as_json(out)


# A resume may change these: the evaluation, the devices, and more training cycles.
_MAY_CHANGE = ("eval", "parallel", "train.cycles")


def open_run(run_dir: Path, config: Config, seeds: Sequence[int], *, resume: bool,
             overwrite: bool) -> None:
    """Check ``run_dir`` before anything in it is touched, then record this run.

    A directory holding a run is refused unless ``resume`` (same task, seeds and config,
    up to the evaluation settings, the devices and a larger ``train.cycles``) or
    ``overwrite`` (its contents are deleted first; it wins over ``resume``).
    """
    path = run_dir / "run.json"
    record = as_json({"version": RUN_VERSION, "task": config.task, "seeds": list(seeds),
                      "config": to_dict(config)})
    barrier("open run: every process reads the directory as it was")
    if path.exists() or (run_dir / "study.json").exists() or (run_dir / "checkpoints").exists():
        if overwrite:
            barrier("overwrite: checked")
            if is_main_process():  # all but the lock this process holds (:func:`locked`)
                for child in (c for c in run_dir.iterdir() if c.name != LOCK):
                    shutil.rmtree(child) if child.is_dir() else child.unlink()
        elif not path.exists():
            raise RunDirError(f"{run_dir} holds a run of an older lazyq-jax; pass --overwrite to "
                              "replace it or pick another --run-dir")
        else:
            stored = json.loads(path.read_text())
            if stored.get("task") != config.task:
                raise RunDirError(f"{run_dir} holds a run of task {stored.get('task')!r}, not "
                                  f"{config.task!r}; pick another --run-dir (or --overwrite)")
            if not resume:
                raise RunDirError(f"{run_dir} already holds a run; continue it with --resume, "
                                  "replace it with --overwrite, or pick another --run-dir")
            if stored.get("version") != RUN_VERSION:
                raise RunDirError(f"{run_dir} holds a run of another lazyq-jax (version "
                                  f"{stored.get('version')}); pass --overwrite to replace it")
            if stored.get("seeds") != list(seeds):
                raise RunDirError(f"{run_dir} holds a run of seeds {stored.get('seeds')}, not "
                                  f"{list(seeds)}; resume it with those, or use another --run-dir")
            old = stored.get("config", {})
            differ = [f for f in config_diff(old, record["config"])
                      if not any(f == m or f.startswith(m + ".") for m in _MAY_CHANGE)
                      and not _added_at_default(old, record["config"], field_defaults(config), f)]
            if differ:
                raise RunDirError(f"{run_dir} holds a run with other settings ({', '.join(differ)}); "
                                  "resume it with its own settings, or use --overwrite")
            if old.get("train", {}).get("cycles", 0) > config.train.cycles:
                raise RunDirError(f"{run_dir} was trained for {old['train']['cycles']} cycles; a resume "
                                  f"may add cycles, not remove them (train.cycles={config.train.cycles})")
    barrier("open run: checked")
    if is_main_process():
        run_dir.mkdir(parents=True, exist_ok=True)
    write_json(path, record)
    barrier("open run: recorded")


def open_method(method_dir: Path, record: dict, defaults: dict | None = None) -> None:
    """Refuse a method directory trained with other settings; record this method's.

    ``defaults``: the record's fields at their defaults; a field the stored record lacks
    (added to lazyq-jax after it was trained) is accepted at its default."""
    path = method_dir / "method.json"
    record = as_json(record)
    defaults = as_json(defaults or {})
    barrier("open method: every process reads it as it was")
    if path.exists():
        stored = json.loads(path.read_text())
        differ = [f for f in config_diff(stored, record)
                  if not _added_at_default(stored, record, defaults, f)]
        if differ:
            raise RunDirError(f"{method_dir} holds {stored.get('method')} trained with other settings "
                              f"({', '.join(differ)}); pass --overwrite or pick another --run-dir")
    barrier("open method: checked")
    write_json(path, record)
