"""Shared fixtures: one PushEnv and one compiled batched push for the whole session.

MJX compiles take seconds on CPU, so tests pad their pushes to a fixed batch.  The suite's
processes (pytest-xdist's workers and the CLI runs they start) share one persistent
compilation cache (``LAZYQ_COMPILE_CACHE``, by default a directory in the system's
temporary directory): a program another process already compiled is read back, not
compiled again.  It changes no result (the cache key is the whole program).
"""

import json
import os
import subprocess
import sys
import tempfile

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lazyq_jax.parallel import enable_compilation_cache
from lazyq_jax.run import load_policy, run
from lazyq_jax.config import Config, TrainConfig
from lazyq_jax.tasks.push import FORGIVING_PUSH, CollectConfig, EvalConfig, PushConfig, PushEnv

PUSH_BATCH = 16

os.environ.setdefault("LAZYQ_COMPILE_CACHE",
                      os.path.join(tempfile.gettempdir(), f"lazyq-jax-test-cache-{os.getuid()}"))
enable_compilation_cache()  # the CLI runs of the tests inherit the variable


def _timeout_scale() -> float:
    raw = os.environ.get("LAZYQ_TEST_TIMEOUT_SCALE", "1")
    try:
        scale = float(raw)
    except ValueError:
        scale = float("nan")
    if not scale > 0 or scale == float("inf"):
        raise pytest.UsageError(f"LAZYQ_TEST_TIMEOUT_SCALE must be a positive number (e.g. 3 when the "
                                f"machine also runs other work), got {raw!r}")
    return scale


TIMEOUT_SCALE = _timeout_scale()


def timeout(seconds: float) -> float:
    """A subprocess's time limit in the suite: ``seconds`` (sized for 2 cores running the suite
    alone, as CI does) times ``LAZYQ_TEST_TIMEOUT_SCALE`` (default 1; raise it when the machine
    also runs other work: the limits catch hangs, not slowness)."""
    return seconds * TIMEOUT_SCALE


def cli(*args, seconds: float = 900) -> subprocess.CompletedProcess:
    """``python -m lazyq_jax ARGS`` in a subprocess, its output captured, within
    :func:`timeout` ``(seconds)``."""
    return subprocess.run([sys.executable, "-m", "lazyq_jax", *args], capture_output=True,
                          text=True, timeout=timeout(seconds), check=False)


POINTMAZE_SMOKE = ["collect.episodes=12", "collect.episode_steps=61", "eval.episodes_per_task=2",
                   "eval.max_steps=20", "train.cycles=2", "neighbours.k=8"]


def pointmaze_round_trip(run_dir, *sets: str) -> None:
    """The pointmaze task at smoke scale with lazy Q and the ``--set`` options ``sets``
    through the CLI: trained, evaluated again to the same outcome, reloaded
    (``load_policy``) and acting in the box."""
    args = ["train", "--task", "pointmaze", "--preset", "smoke", "--run-dir", str(run_dir), "--no-progress"]
    for a in [*POINTMAZE_SMOKE, *sets]:
        args += ["--set", a]
    out = cli(*args)
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-3000:]
    first = json.loads((run_dir / "results.json").read_text())["methods"]["lazy"]["per_seed"]
    out = cli("evaluate", "--run-dir", str(run_dir), "--methods", "lazy", "--no-figures", "--no-progress")
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-3000:]
    assert json.loads((run_dir / "results.json").read_text())["methods"]["lazy"]["per_seed"] == first
    act = load_policy(run_dir, "lazy")
    a = act(jax.random.PRNGKey(0), jnp.zeros((3, 2)), jnp.full((3, 2), 4.0))
    assert a.shape == (3, 2) and bool(jnp.all(jnp.abs(a) <= 1.0 + 1e-6))


@pytest.fixture(scope="session")
def env() -> PushEnv:
    return PushEnv(PushConfig())


def batched_push(env: PushEnv):
    """``push(finger[B,2], action[B,2], disk[B,2]=0) -> (finger_after, disk_delta)`` as NumPy,
    padded to one compiled batch of :data:`PUSH_BATCH`."""
    step = jax.jit(jax.vmap(env.step))

    def run(finger, action, disk=None):
        finger = np.asarray(finger, np.float32).reshape(-1, 2)
        action = np.asarray(action, np.float32).reshape(-1, 2)
        disk = np.zeros_like(finger) if disk is None else np.asarray(disk, np.float32).reshape(-1, 2)
        n = finger.shape[0]
        assert n <= PUSH_BATCH
        pad = lambda x, fill: np.concatenate([x, np.tile(fill, (PUSH_BATCH - n, 1))]).astype(np.float32)
        state = env.reset(pad(finger, [0.9, 0.9]), pad(disk, [0.0, 0.0]))
        nxt, delta = step(state, jnp.asarray(pad(action, [1.0, 0.0])))
        return np.asarray(nxt.finger_xy)[:n], np.asarray(delta)[:n]

    return run


@pytest.fixture(scope="session")
def push(env):
    """Pushes in the paper's world (the default PushConfig)."""
    return batched_push(env)


@pytest.fixture(scope="session")
def push_forgiving():
    """Pushes in the forgiving world (quadratic drag, preset ``forgiving``)."""
    return batched_push(PushEnv(FORGIVING_PUSH))


# A small but real push run: dense data near the disk so a few cycles propagate value.
PUSH = Config(
    task="push",
    seed=1,
    collect=CollectConfig(n_starts=1200, n_goals=24, start_range=0.6, chunk_size=1200),
    train=TrainConfig(cycles=4, epochs=3, batch_size=512, width=64, target_batch_size=16384),
    eval=EvalConfig(n_directions=4, episodes_per_direction=6, max_steps=20, start_range=0.6,
                    long_rollouts=4, long_max_steps=30),
)


@pytest.fixture(scope="session")
def push_run(tmp_path_factory):
    """The run directory of :data:`PUSH` (one seed, lazy Q), trained and evaluated once per
    session (per worker)."""
    run_dir = tmp_path_factory.mktemp("push_run")
    run(PUSH, run_dir, progress=False)
    return run_dir


# The files whose tests take longest (minutes, mostly compilation; measured with
# ``make test ARGS=--durations=40``), longest first.  ``make test`` hands whole files to
# its workers in collection order (``--dist loadfile --no-loadscope-reorder``): starting
# the long files first keeps one worker from running a long file alone at the end.
LONG_FILES = ("test_parallel.py", "test_study_arms.py", "test_study.py", "test_online.py",
              "test_lazy_push.py", "test_agents.py", "test_pointmaze.py", "test_readme.py")


def pytest_collection_modifyitems(items):
    rank = {name: i for i, name in enumerate(LONG_FILES)}
    items.sort(key=lambda item: rank.get(item.path.name, len(LONG_FILES)))  # stable: file order kept
