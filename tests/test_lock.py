"""The run directory's lock (:func:`lazyq_jax.run.rundir.locked`): a second process on a
directory another live process holds is refused at once, naming the holder, and touches
nothing; a killed holder's lock is taken over (and its run resumes); of processes starting
at the same moment exactly one gets it; ``--overwrite`` keeps it."""

import json
import os
import signal
import subprocess
import sys
import time

import pytest
from conftest import cli, timeout

from lazyq_jax import tasks
from lazyq_jax.config import to_dict
from lazyq_jax.run import RunDirError, locked
from lazyq_jax.run.rundir import LOCK, open_run, read_jsonl

# A python process that takes the lock of argv[1] (after waiting for the file argv[2], if
# given), says whether it got it, and holds it until it is killed or argv[3] appears.
TAKER = """
import os, sys, time
from pathlib import Path
from lazyq_jax.run import RunDirError, locked
go, done = (Path(a) for a in (sys.argv[2:] + ["", ""])[:2])
print("ready", flush=True)
while go.name and not go.exists():
    time.sleep(0.001)
try:
    with locked(Path(sys.argv[1])):
        print("got", os.getpid(), flush=True)
        while not (done.name and done.exists()):
            time.sleep(0.01)
except RunDirError as e:
    print("refused", e, flush=True)
"""


def taker(*args) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", TAKER, *map(str, args)], stdout=subprocess.PIPE,
                            text=True)


def wait_line(p: subprocess.Popen, start: str) -> str:
    line = p.stdout.readline()
    assert line.startswith(start), line
    return line


def snapshot(d):
    return {str(p): (p.stat().st_mtime_ns, p.read_bytes()) for p in sorted(d.rglob("*")) if p.is_file()}


def smoke_run_json(run_dir):
    """A run.json as ``train --preset smoke`` writes it (so that ``evaluate`` gets as far as the lock)."""
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "run.json").write_text(json.dumps(
        {"version": 2, "task": "push", "seeds": [0], "config": to_dict(tasks.preset("push", "smoke"))}))


def test_a_held_directory_is_refused_at_once_naming_the_holder(tmp_path):
    run_dir = tmp_path / "run"
    smoke_run_json(run_dir)
    holder = taker(run_dir)
    try:
        wait_line(holder, "ready")
        pid = int(wait_line(holder, "got").split()[1])
        before = snapshot(run_dir)
        for command in ("train", "evaluate", "collect"):  # study: train's path, plot: evaluate's
            extra = [] if command == "evaluate" else ["--preset", "smoke"]
            out = cli(command, "--run-dir", str(run_dir), "--no-progress", *extra, seconds=120)
            assert out.returncode == 2, (command, out.stderr[-2000:])
            assert f"in use by process {pid} on " in out.stderr, out.stderr
            assert snapshot(run_dir) == before, command
        with pytest.raises(RunDirError, match=f"process {pid} on .*: {sys.executable} -c"), locked(run_dir):
            pass  # in-process too
    finally:
        holder.kill()
        holder.wait()


def test_a_killed_holders_lock_is_taken_over(tmp_path):
    holder = taker(tmp_path)
    wait_line(holder, "ready")
    wait_line(holder, "got")
    os.kill(holder.pid, signal.SIGKILL)
    holder.wait()
    assert json.loads((tmp_path / LOCK).read_text())["pid"] == holder.pid  # left behind
    with locked(tmp_path):
        assert json.loads((tmp_path / LOCK).read_text())["pid"] == os.getpid()


def test_of_processes_starting_at_once_exactly_one_gets_it(tmp_path):
    run_dir, go, done = tmp_path / "run", tmp_path / "go", tmp_path / "done"
    racers = [taker(run_dir, go, done) for _ in range(3)]
    try:
        for p in racers:
            wait_line(p, "ready")
        go.touch()  # every racer polls for it every millisecond
        first = [p.stdout.readline().split() for p in racers]
        winners = [int(words[1]) for words in first if words[0] == "got"]
        assert len(winners) == 1, first
        losers = [" ".join(words) for words in first if words[0] == "refused"]
        assert len(losers) == 2 and all(f"process {winners[0]} on " in text for text in losers), first
        assert json.loads((run_dir / LOCK).read_text())["pid"] == winners[0]  # written whole
    finally:
        done.touch()
        for p in racers:
            p.wait(timeout=timeout(60))


def test_overwrite_keeps_the_lock(tmp_path):
    config = tasks.preset("push", "smoke")
    with locked(tmp_path):
        open_run(tmp_path, config, [0], resume=False, overwrite=False)
        (tmp_path / "data").mkdir()
        open_run(tmp_path, config, [0], resume=False, overwrite=True)
        assert sorted(p.name for p in tmp_path.iterdir()) == [LOCK, "run.json"]
        with pytest.raises(RunDirError, match=f"process {os.getpid()} on "), locked(tmp_path):
            pass  # still held


def test_a_run_killed_mid_training_resumes(tmp_path):
    """``kill -9`` in the middle of ``train``: its lock is taken over, and ``--resume``
    trains the blocks it lacked, each once."""
    blocks = 40
    args = ["train", "--preset", "smoke", "--run-dir", str(tmp_path), "--no-progress", "--no-eval"]
    for a in ("collect.n_starts=150", "collect.n_goals=8", f"train.cycles={blocks}", "train.epochs=1",
              "train.batch_size=64", "train.width=16"):
        args += ["--set", a]
    metrics = tmp_path / "lazy" / "metrics.jsonl"
    first = subprocess.Popen([sys.executable, "-m", "lazyq_jax", *args], stdout=subprocess.DEVNULL,
                             stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + timeout(600)
    while not read_jsonl(metrics) and first.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    first.kill()
    first.wait()
    done = len(read_jsonl(metrics))
    assert 0 < done < blocks, done  # killed in the middle of training
    out = cli(*args, "--resume", seconds=600)
    assert out.returncode == 0, out.stderr[-3000:]
    assert "resuming after block " in out.stderr + out.stdout
    assert [r["block"] for r in read_jsonl(metrics)] == list(range(1, blocks + 1))
