"""Lazy Q on a small but real push run (the session's ``push_run``, one seed): training
(loss, value, the clip of Eq. 8, DQN against Double DQN), checkpoints, the trained
policy, and re-evaluating the run."""

import json
import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import PUSH
from lazyq_jax.checkpoint import (CheckpointDamaged, CheckpointError, all_steps, checkpoint_writer,
                                  load_checkpoint, save_checkpoint)
from lazyq_jax.config import override
from lazyq_jax.run import evaluate_run, load_run
from lazyq_jax.targets import dataset_targets, in_sample_target, lazy_target, local_fits
from lazyq_jax.train import make_train


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


def test_target_max_over_the_data_in_a_cycle(trained):
    """``train.target_max=data``: the cycle's targets are ``alpha + max_j beta . a_j`` over
    each neighbourhood's actions (by hand from the frozen network's fits), and on average
    below Eq. (7)'s maximum over the ball that holds those actions."""
    _, _, data, idx = trained
    cfg = override(PUSH, ["train.target_max=data", "train.epochs=1"]).train
    trainer = make_train(cfg, 0.1, state_scale=0.6)
    state = trainer.init(jax.random.PRNGKey(0), data)
    alpha, beta, y_nb = local_fits(trainer.value_fn(state), data, idx, gamma=cfg.gamma)
    expect, _ = lazy_target(alpha, beta, y_nb, 0.1, cfg.clip, "ball", data.a[idx])
    ball, _ = lazy_target(alpha, beta, y_nb, 0.1, cfg.clip, "ball")
    _, metrics = jax.jit(trainer.run_cycle)(state, data, idx)
    n = data.size  # float32 means of n rows summed in another order
    np.testing.assert_allclose(float(metrics["target_mean"]), float(jnp.mean(expect)),
                               rtol=max(n * 2.0 ** -24, 1e-6))
    assert float(jnp.mean(expect)) < float(jnp.mean(ball))


@pytest.mark.parametrize("model", ["action", "action+state"])
def test_target_max_expectile_in_a_cycle(trained, model):
    """``train.target_max=expectile``: the cycle's targets are the 0.9-expectile of the
    neighbours' values moved to the row (the values themselves with the paper's action-only
    model, moved by the state offsets' coefficients otherwise), computed by hand from the
    frozen network; Eq. (8)'s clip is never active; and they lie below Eq. (7)'s maximum."""
    _, _, data, idx = trained
    cfg = override(PUSH, ["train.target_max=expectile", "train.epochs=1"]).train
    offsets = model != "action"
    trainer = make_train(cfg, 0.1, state_scale=0.6, state_offsets=offsets)
    state = trainer.init(jax.random.PRNGKey(0), data)
    v = trainer.value_fn(state)
    alpha, beta, moved = local_fits(v, data, idx, gamma=cfg.gamma, state_offsets=offsets, in_sample=True)
    expect, _ = in_sample_target(moved, 0.9)
    if not offsets:
        _, _, y_nb = local_fits(v, data, idx, gamma=cfg.gamma)
        np.testing.assert_array_equal(moved, y_nb)
    ball, _ = lazy_target(alpha, beta, moved, 0.1, cfg.clip, "ball")
    _, metrics = jax.jit(trainer.run_cycle)(state, data, idx)
    n = data.size  # float32 means of n rows summed in another order
    np.testing.assert_allclose(float(metrics["target_mean"]), float(jnp.mean(expect)),
                               rtol=max(n * 2.0 ** -24, 1e-6))
    assert float(metrics["clip_fraction"]) == 0.0
    assert float(jnp.mean(expect)) < float(jnp.mean(ball))


def test_checkpoint_round_trip_is_exact(tmp_path, trained):
    state = trained[0]
    save_checkpoint(tmp_path / "ck", state, 4, {"note": "x"})
    restored, meta = load_checkpoint(tmp_path / "ck", jax.eval_shape(lambda: state))
    assert meta["note"] == "x" and meta["step"] == 4
    assert tree_equal(restored, state)
    assert jax.tree.structure(restored) == jax.tree.structure(state)


def test_checkpoint_writer_saves_every_step_as_save_checkpoint_does(tmp_path, trained):
    """One manager for many saves (the runner's blocks): every step is listed, restores
    exactly, carries its own metadata, and has its checksums (damage is recognised)."""
    state = trained[0]
    abstract = jax.eval_shape(lambda: state)
    bumped = jax.tree.map(lambda x: x + 1 if jnp.issubdtype(x.dtype, jnp.floating) else x, state)
    with checkpoint_writer(tmp_path / "ck") as save:
        for step, st in ((1, state), (2, bumped), (3, state)):
            assert save(st, step, {"block": step}) == tmp_path / "ck" / str(step)
    assert all_steps(tmp_path / "ck") == [1, 2, 3]
    for step, st in ((1, state), (2, bumped), (3, state)):
        restored, meta = load_checkpoint(tmp_path / "ck", abstract, step)
        assert tree_equal(restored, st) and meta["block"] == step and meta["step"] == step
    assert (tmp_path / "ck" / "2" / "checksums.json").exists()
    victim = next(p for p in sorted((tmp_path / "ck" / "3" / "state").rglob("*")) if p.is_file()
                  and p.stat().st_size > 0)
    victim.write_bytes(victim.read_bytes()[:-1])  # truncated
    with pytest.raises(CheckpointDamaged, match="damaged or truncated"):
        load_checkpoint(tmp_path / "ck", abstract, 3)


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


def test_policy_pushes_from_behind_toward_the_goal(push_run):
    act = load_run(push_run).policy()
    goals = jnp.array([0.0, np.pi / 2, np.pi, -np.pi / 2])
    direction = np.stack([np.cos(goals), np.sin(goals)], 1)
    behind = jnp.asarray(-0.36 * direction, jnp.float32)  # finger on the far side from the goal
    action = np.asarray(act(jax.random.PRNGKey(0), behind, goals))
    np.testing.assert_allclose(np.linalg.norm(action, axis=1), 0.1, rtol=1e-5)
    cos = np.sum(action * direction, axis=1) / 0.1
    assert np.all(cos > 0.7), cos


def test_results_schema_determinism_and_figures(push_run):
    first = evaluate_run(push_run, progress=False)
    saved = json.loads((push_run / "lazy" / "eval.json").read_text())
    assert saved["block"] == PUSH.train.cycles and saved["seeds"] == [PUSH.seed]
    result = saved["per_seed"][0]
    a, b = result["protocol_a"], result["protocol_b"]
    assert len(a["per_goal"]) == PUSH.eval.n_directions
    for row in a["per_goal"]:
        assert set(row) == {"goal", "correct", "wrong", "not_pushed"}
        assert row["correct"] + row["wrong"] + row["not_pushed"] == PUSH.eval.episodes_per_direction
    assert 0 <= a["axis_correct_rate"] <= 1 and 0 <= a["overall_correct_rate"] <= 1
    assert b["rollouts"] == PUSH.eval.long_rollouts and 0 <= b["successes"] <= b["rollouts"]
    assert result["seed"] == PUSH.seed and result["eval_seed"] == PUSH.seed + PUSH.eval.seed
    for name in ("fig3_value.png", "fig4_outcomes.png", "fig5_long_horizon.png"):
        path = push_run / "figures" / "lazy" / name
        assert path.stat().st_size > 10_000 and path.read_bytes()[:4] == b"\x89PNG"
    gif = push_run / "figures" / "lazy" / "rollouts.gif"
    assert gif.read_bytes()[:6] == b"GIF89a" and gif.stat().st_size > 10_000
    again = evaluate_run(push_run, figures=False, progress=False)
    assert again["methods"]["lazy"]["per_seed"] == first["methods"]["lazy"]["per_seed"]
    other = evaluate_run(push_run, figures=False, progress=False, overrides=["eval.seed=5"])
    assert json.loads((push_run / "lazy" / "eval.json").read_text())["per_seed"][0]["eval_seed"] == \
        PUSH.seed + 5
    assert other["methods"]["lazy"]["per_seed"] != first["methods"]["lazy"]["per_seed"]
