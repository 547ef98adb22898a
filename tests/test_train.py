"""Training, checkpoints and resume on tiny configs."""

import json
import shutil
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lazyq_jax.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from lazyq_jax.config import TrainConfig, override
from lazyq_jax.neighbours import find_neighbours
from lazyq_jax.pipeline import RunDirError, fit, neighbours_for, prepare_dataset
from lazyq_jax.train import make_train, make_train_for
from lazyq_jax.types import Transitions

from conftest import PUSH

TINY = override(PUSH, ["collect.n_starts=150", "collect.n_goals=8", "train.cycles=3",
                       "train.epochs=2", "train.width=16", "train.batch_size=128"])


def tree_equal(a, b):
    return all(jax.tree.leaves(jax.tree.map(lambda x, y: bool(np.array_equal(x, y)), a, b)))


def test_loss_falls_and_value_is_high_behind_the_disk(push_run):
    run_dir, state, trainer, _ = push_run
    lines = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    assert [m["cycle"] for m in lines] == [1, 2, 3, 4]
    assert lines[-1]["loss"] < lines[0]["loss_first_epoch"]
    v = trainer.value_fn(state)
    # finger just behind the disk for the goal (one push away from +1) vs finger far away
    behind = v(jnp.array([[-0.35, 0.0], [0.0, -0.35]]), jnp.array([0.0, np.pi / 2]))
    far = v(jnp.array([[0.55, 0.55], [0.55, 0.55]]), jnp.array([0.0, np.pi / 2]))
    assert np.all(np.asarray(behind) > np.asarray(far) + 0.2), (behind, far)


def test_targets_respect_the_clip(push_run):
    _, state, trainer, data = push_run
    from lazyq_jax.targets import dataset_targets

    idx = neighbours_for(PUSH, data)
    v = trainer.value_fn(state)
    y_clipped, diag = dataset_targets(v, data, idx, gamma=0.9, action_length=0.1, clip=True)
    y_free, _ = dataset_targets(v, data, idx, gamma=0.9, action_length=0.1, clip=False)
    values = data.r + 0.9 * (1 - data.done) * v(data.s_next, data.g)
    bound = np.asarray(jnp.max(values[idx], axis=1))
    y_clipped, y_free, active = map(np.asarray, (y_clipped, y_free, diag.clip_active))
    assert np.all(y_clipped <= bound + 1e-5)
    # where the clip is active the target is the neighbour bound, elsewhere Eq. (7)'s value
    np.testing.assert_allclose(y_clipped[active], bound[active], atol=1e-5)
    np.testing.assert_allclose(y_clipped[~active], y_free[~active], atol=1e-6)
    assert np.all(y_free[active] > bound[active])
    assert 0 < active.mean() < 1


def test_dqn_and_double_dqn_both_run_and_differ(push_run):
    _, _, _, data = push_run
    idx = neighbours_for(PUSH, data)
    results = {}
    for double in (False, True):
        cfg = override(PUSH, [f"train.double_dqn={double}", "train.epochs=2"])
        trainer = make_train_for(cfg)
        state = trainer.init(jax.random.PRNGKey(0))
        state, _ = trainer.run_cycle(state, data, idx)  # cycle 1: online == frozen at start
        state, metrics = jax.jit(trainer.run_cycle)(state, data, idx)
        assert np.isfinite(float(metrics["loss"]))
        results[double] = state.params
    assert not tree_equal(results[False], results[True])


def test_checkpoint_round_trip_is_exact(tmp_path, push_run):
    _, state, _, _ = push_run
    save_checkpoint(tmp_path / "ck", state, PUSH)
    restored, config = load_checkpoint(tmp_path / "ck")
    assert config == PUSH
    assert tree_equal(restored, state)
    assert jax.tree.structure(restored) == jax.tree.structure(state)


def test_bad_checkpoints_give_clear_errors(tmp_path, push_run):
    _, state, _, _ = push_run
    with pytest.raises(CheckpointError, match="no checkpoint"):
        load_checkpoint(tmp_path / "nothing")
    save_checkpoint(tmp_path / "ck", state, PUSH)
    wider = override(PUSH, ["train.width=128"])
    with pytest.raises(CheckpointError, match="train.width: checkpoint 64 vs requested 128"):
        load_checkpoint(tmp_path / "ck", expect=wider)
    # a checkpoint whose arrays were removed (a partial copy) is named, not a crash in JAX
    step = tmp_path / "ck" / str(int(state.cycle))
    shutil.rmtree(step / "state")
    with pytest.raises(CheckpointError, match=str(step)):
        load_checkpoint(tmp_path / "ck")


@pytest.mark.parametrize("flags", [[], ["train.resample_neighbours=true", "train.double_dqn=true"]])
def test_resume_equals_uninterrupted_run(tmp_path, flags):
    config = override(TINY, flags)
    full, _, _ = fit(config, tmp_path / "full", progress=False)
    first, _, _ = fit(override(config, ["train.cycles=2"]), tmp_path / "cut", progress=False)
    assert int(first.cycle) == 2
    resumed, _, _ = fit(config, tmp_path / "cut", resume=True, progress=False)
    assert int(resumed.cycle) == 3
    assert tree_equal(resumed, full)  # params, batch stats, optimiser state, key, cycle
    lines = (tmp_path / "cut" / "metrics.jsonl").read_text().splitlines()
    assert [json.loads(line)["cycle"] for line in lines] == [1, 2, 3]


def test_resume_skips_a_damaged_newest_checkpoint(tmp_path, capsys):
    """A truncated file in the newest checkpoint: resume warns, moves it aside (nothing is
    deleted), continues from the newest intact one, and ends as an uninterrupted run."""
    full, _, _ = fit(TINY, tmp_path / "full", progress=False)
    run = tmp_path / "cut"
    fit(TINY, run, progress=False)
    victim = max((p for p in (run / "checkpoints" / "3" / "state").rglob("*") if p.is_file()),
                 key=lambda p: p.stat().st_size)
    victim.write_bytes(victim.read_bytes()[: victim.stat().st_size // 2])
    with pytest.raises(CheckpointError, match="damaged or truncated"):
        load_checkpoint(run / "checkpoints")
    capsys.readouterr()
    resumed, _, _ = fit(TINY, run, resume=True, progress=False)
    log = capsys.readouterr().out
    assert "checkpoints/3" in log and "damaged or truncated" in log and "resume: from cycle 2" in log
    assert (run / "checkpoints_damaged" / "3").is_dir()
    assert tree_equal(resumed, full)
    lines = (run / "metrics.jsonl").read_text().splitlines()
    assert [json.loads(line)["cycle"] for line in lines] == [1, 2, 3]


def test_damaged_checkpoint_error_through_the_cli_has_no_traceback(tmp_path):
    run = tmp_path / "run"
    args = [sys.executable, "-m", "lazyq_jax", "train", "--preset", "smoke", "--run-dir", str(run),
            "--no-eval", "--no-progress", "--set", "collect.n_starts=100", "--set", "train.cycles=1"]
    assert subprocess.run(args, capture_output=True, timeout=600).returncode == 0
    for p in (run / "checkpoints" / "1" / "state").rglob("*"):
        if p.is_file():
            p.write_bytes(b"\0" * 7)
    evaluate = subprocess.run([sys.executable, "-m", "lazyq_jax", "evaluate", "--run-dir", str(run)],
                              capture_output=True, text=True, timeout=600)
    assert evaluate.returncode == 2 and "damaged or truncated" in evaluate.stderr
    assert "Traceback" not in evaluate.stderr, evaluate.stderr[-2000:]
    resumed = subprocess.run(args + ["--resume"], capture_output=True, text=True, timeout=600)
    assert resumed.returncode == 0 and "starting afresh" in resumed.stdout + resumed.stderr
    assert "Traceback" not in resumed.stderr


def test_run_directory_is_not_overwritten_by_accident(tmp_path):
    small = override(TINY, ["train.cycles=1"])
    fit(small, tmp_path, progress=False)
    dataset = (tmp_path / "dataset.npz").read_bytes()
    with pytest.raises(RunDirError, match="--resume"):
        fit(small, tmp_path, progress=False)
    # a resume with an incompatible config is refused before anything is rewritten
    with pytest.raises(CheckpointError, match="collect config or seed differ"):
        fit(override(small, ["collect.n_goals=5"]), tmp_path, resume=True, progress=False)
    assert (tmp_path / "dataset.npz").read_bytes() == dataset
    state, _, _ = fit(small, tmp_path, overwrite=True, progress=False)
    assert int(state.cycle) == 1
    # --overwrite wins over --resume (make train always passes --resume): an incompatible
    # checkpoint is replaced, not refused
    wider = override(small, ["train.width=24"])
    state, _, _ = fit(wider, tmp_path, resume=True, overwrite=True, progress=False)
    assert int(state.cycle) == 1 and state.params["Dense_0"]["kernel"].shape[-1] == 24


def test_train_is_task_agnostic():
    # A point that moves by its action; reward 1 on reaching a goal disc around g's
    # direction: nothing of the push task.  The pure train() runs all cycles in one scan.
    rng = np.random.default_rng(0)
    n = 6000
    s = rng.uniform(-1, 1, (n, 2)).astype(np.float32)
    phi = rng.uniform(-np.pi, np.pi, n)
    a = (0.1 * np.stack([np.cos(phi), np.sin(phi)], 1)).astype(np.float32)
    g = rng.uniform(-np.pi, np.pi, n).astype(np.float32)
    target = 0.7 * np.stack([np.cos(g), np.sin(g)], 1)
    done = np.linalg.norm(s + a - target, axis=1) < 0.2
    data = Transitions(s=jnp.asarray(s), a=jnp.asarray(a), s_next=jnp.asarray(s + a),
                       r=jnp.asarray(done, jnp.float32), g=jnp.asarray(g), done=jnp.asarray(done))
    idx = find_neighbours(jax.random.PRNGKey(0), data.s, data.g, data.s, data.g, k=10,
                          radius_s=0.15, radius_g=0.3).idx
    trainer = make_train(TrainConfig(cycles=3, epochs=8, width=32, batch_size=128), 0.1)
    state, metrics = jax.jit(trainer.train)(jax.random.PRNGKey(0), data, idx)
    assert int(state.cycle) == 3
    assert np.all(np.isfinite(np.asarray(metrics["loss"])))
    v = trainer.value_fn(state)
    near = v(jnp.asarray(target[:200] * 0.85, jnp.float32), data.g[:200])
    away = v(jnp.asarray(-target[:200], jnp.float32), data.g[:200])
    assert float(jnp.mean(near)) > float(jnp.mean(away)) + 0.1, (jnp.mean(near), jnp.mean(away))


def test_smoke_preset_through_the_cli(tmp_path):
    run_dir = tmp_path / "smoke"
    out = subprocess.run([sys.executable, "-m", "lazyq_jax", "train", "--preset", "smoke",
                          "--run-dir", str(run_dir), "--no-progress"],
                         capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    assert (run_dir / "dataset.npz").exists() and (run_dir / "config.json").exists()
    lines = (run_dir / "metrics.jsonl").read_text().splitlines()
    assert len(lines) == 3 and (run_dir / "checkpoints" / "3").is_dir()
    bad = subprocess.run([sys.executable, "-m", "lazyq_jax", "train", "--set", "train.widht=3"],
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "unknown config field 'train.widht'" in bad.stderr


def test_dataset_cache_is_reused_only_for_the_same_config(tmp_path):
    small = override(TINY, ["collect.n_starts=20", "collect.n_goals=2"])
    first = prepare_dataset(small, tmp_path, progress=False)
    stamp = (tmp_path / "dataset.npz").stat().st_mtime_ns
    again = prepare_dataset(small, tmp_path, progress=False)
    assert (tmp_path / "dataset.npz").stat().st_mtime_ns == stamp
    np.testing.assert_array_equal(first.s, again.s)
    other = prepare_dataset(override(small, ["seed=9"]), tmp_path, progress=False)
    assert not np.array_equal(np.asarray(other.s)[:4], np.asarray(first.s)[:4])
