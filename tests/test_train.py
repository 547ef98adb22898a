"""Training (§IV-E) on the session's push run and on tasks that are not the push: loss, value,
the clip of Eq. (8), DQN against Double DQN, sizes from the data, checkpoints."""

import json
import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lazyq_jax.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from lazyq_jax.config import TrainConfig, override
from lazyq_jax.neighbours import find_neighbours
from lazyq_jax.run import load_run
from lazyq_jax.targets import dataset_targets
from lazyq_jax.train import make_train
from lazyq_jax.types import Transitions

from conftest import PUSH


def tree_equal(a, b):
    return all(jax.tree.leaves(jax.tree.map(lambda x, y: bool(np.array_equal(x, y)), a, b)))


@pytest.fixture(scope="module")
def trained(push_run):
    """``(state, trainer, data, idx)`` of the session's push run (one seed)."""
    loaded = load_run(push_run)
    data = loaded.data.seed_data(0)
    idx = loaded.agent.prepare(PUSH.seed, data, data.size, 0).idx
    return loaded.state(), loaded.agent.trainer, data, idx


def test_loss_falls_and_value_is_high_behind_the_disk(push_run, trained):
    state, trainer, _, _ = trained
    lines = [json.loads(line) for line in (push_run / "lazy" / "metrics.jsonl").read_text().splitlines()]
    assert [m["block"] for m in lines] == [1, 2, 3, 4]
    assert lines[-1]["loss"][0] < lines[0]["loss_first_epoch"][0]
    v = trainer.value_fn(state)
    # finger just behind the disk for the goal (one push away from +1) vs finger far away
    behind = v(jnp.array([[-0.35, 0.0], [0.0, -0.35]]), jnp.array([0.0, np.pi / 2]))
    far = v(jnp.array([[0.55, 0.55], [0.55, 0.55]]), jnp.array([0.0, np.pi / 2]))
    assert np.all(np.asarray(behind) > np.asarray(far) + 0.2), (behind, far)


def test_targets_respect_the_clip(trained):
    state, trainer, data, idx = trained
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


def test_dqn_and_double_dqn_both_run_and_differ(trained):
    _, _, data, idx = trained
    results = {}
    for double in (False, True):
        cfg = override(PUSH, [f"train.double_dqn={double}", "train.epochs=2"]).train
        trainer = make_train(cfg, 0.1, state_scale=0.6)
        state = trainer.init(jax.random.PRNGKey(0), data)
        state, _ = trainer.run_cycle(state, data, idx)  # cycle 1: online == frozen at start
        state, metrics = jax.jit(trainer.run_cycle)(state, data, idx)
        assert np.isfinite(float(metrics["loss"]))
        results[double] = state.params
    assert not tree_equal(results[False], results[True])


def test_checkpoint_round_trip_is_exact(tmp_path, trained):
    state = trained[0]
    save_checkpoint(tmp_path / "ck", state, 4, {"note": "x"})
    restored, meta = load_checkpoint(tmp_path / "ck", jax.eval_shape(lambda: state))
    assert meta["note"] == "x" and meta["step"] == 4
    assert tree_equal(restored, state)
    assert jax.tree.structure(restored) == jax.tree.structure(state)


def test_bad_checkpoints_give_clear_errors(tmp_path, trained):
    state = trained[0]
    abstract = jax.eval_shape(lambda: state)
    with pytest.raises(CheckpointError, match="no checkpoint"):
        load_checkpoint(tmp_path / "nothing", abstract)
    save_checkpoint(tmp_path / "ck", state, 4)

    def refuse(path, meta):
        raise CheckpointError(f"{path}: not this one")

    with pytest.raises(CheckpointError, match="not this one"):
        load_checkpoint(tmp_path / "ck", abstract, check=refuse)
    # a checkpoint whose arrays were removed (a partial copy) is named, not a crash in JAX
    shutil.rmtree(tmp_path / "ck" / "4" / "state")
    with pytest.raises(CheckpointError, match=str(tmp_path / "ck" / "4")):
        load_checkpoint(tmp_path / "ck", abstract)


def point_task(n=6000, d=2, goal="angle", seed=0):
    """A point that moves by its action; reward 1 on reaching a goal disc around g's direction
    (or, without goals, a fixed target): nothing of the push task."""
    rng = np.random.default_rng(seed)
    s = rng.uniform(-1, 1, (n, d)).astype(np.float32)
    a = rng.normal(size=(n, d))
    a = (0.1 * a / np.linalg.norm(a, axis=1, keepdims=True)).astype(np.float32)
    if goal == "angle":
        g = rng.uniform(-np.pi, np.pi, n).astype(np.float32)
        target = 0.7 * np.stack([np.cos(g), np.sin(g)], 1)
    elif goal is None:
        g, target = None, np.full((n, d), 0.5)
    else:
        target = rng.uniform(-0.7, 0.7, (n, goal)).astype(np.float32)
        g = target
    done = np.linalg.norm(s + a - target, axis=1) < 0.2
    data = Transitions(s=jnp.asarray(s), a=jnp.asarray(a), s_next=jnp.asarray(s + a),
                       r=jnp.asarray(done, jnp.float32), g=None if g is None else jnp.asarray(g),
                       done=jnp.asarray(done))
    return data, target


def test_train_is_task_agnostic():
    data, target = point_task()
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


def test_sizes_come_from_the_data_and_mismatches_are_named():
    """A trainer takes the network's input from the data (vector goals, 3-D states here); a
    trainer or state built for other sizes is refused with both sizes, never a flax error."""
    data, _ = point_task(n=400, d=3, goal=3)
    idx = jnp.zeros((400, 4), jnp.int32)
    trainer = make_train(TrainConfig(cycles=1, epochs=1, width=8, depth=2, batch_size=64), 0.1)
    state, _ = jax.jit(trainer.train)(jax.random.PRNGKey(0), data, idx)
    assert state.params["Dense_0"]["kernel"].shape == (6, 8)  # 3 state + 3 goal inputs
    fixed = make_train(TrainConfig(cycles=1, epochs=1, width=8, depth=2), 0.1, state_dim=2, goal="angle")
    with pytest.raises(ValueError, match=r"built for states s\[N, 2\] with angle goals.*"
                                         r"states s\[N, 3\] with goals g\[N, 3\]"):
        fixed.train(jax.random.PRNGKey(0), data, idx)
    other, _ = point_task(n=400, d=2, goal="angle")
    with pytest.raises(ValueError, match="inputs of width 6.*width 4"):
        trainer.run_cycle(state, other, idx)
    with pytest.raises(ValueError, match="needs example data"):
        trainer.init(jax.random.PRNGKey(0))
    with pytest.raises(ValueError, match="state_scale has 2 entries but the states have 3"):
        make_train(TrainConfig(), 0.1, state_scale=(1.0, 2.0)).init(jax.random.PRNGKey(0), data)
