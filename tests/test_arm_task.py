"""The arm task (lazyq_jax.arm_task): the disk in the state (arm-long), its data, the
long-horizon task, and a whole ``fit_arm`` run that is stopped and resumed."""

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lazyq_jax.arm_task import (ARM_TASKS, ArmTask, arm_protocol_b, check_arm_overrides, collect_arm,
                                fit_arm)
from lazyq_jax.checkpoint import load_checkpoint
from lazyq_jax.cli import main as cli_main
from lazyq_jax.config import CollectConfig, ConfigError, EvalConfig, NeighbourConfig, TrainConfig, preset
from lazyq_jax.data import load_dataset
from lazyq_jax.env.arm import ArmConfig, ArmEnv, fingertip_xy
from lazyq_jax.evaluate import CORRECT, NOT_PUSHED, WRONG
from lazyq_jax.neighbours import find_neighbours
from lazyq_jax.pipeline import RunDirError, run_keys
from lazyq_jax.train import make_train

ARM = ArmConfig()
LONG = ARM_TASKS["arm-long"]


def test_arm_task_validation():
    assert ArmTask().state_dim == 3 and LONG.state_dim == 5
    for bad in ({"disk_range": -0.1}, {"disk_range": float("nan")}, {"disk_scale": 0},
                {"long_range": True}, {"disk_range": 0.2, "long_range": 0.3}):
        with pytest.raises(ConfigError):
            ArmTask(**bad)
    with pytest.raises(ConfigError, match="disk in the state"):
        arm_protocol_b(ArmEnv(ARM), None, jax.random.PRNGKey(0), EvalConfig(), ArmTask())


def test_overrides_the_arm_ignores_are_refused(capsys, monkeypatch):
    check_arm_overrides(["train.width=64", "eval.n_directions=4", "collect.n_goals=8"])
    for assignment, hint in (("eval.long_range=0.2", "ArmTask.long_range"),
                             ("collect.start_range=0.5", "random joint angles"),
                             ("online.rounds=2", "offline only"), ("parallel.devices=2", "one device")):
        with pytest.raises(ConfigError, match=hint):
            check_arm_overrides([assignment])
    # the CLI refuses them before it builds anything
    monkeypatch.setenv("LAZYQ_COMPILE_CACHE", "off")  # main() would turn the disk cache on
    with pytest.raises(SystemExit) as exit_:
        cli_main(["train", "--task", "arm", "--set", "eval.long_range=0.2"])
    assert exit_.value.code == 2 and "no effect on the arm task" in capsys.readouterr().err


def test_arm_long_data_put_the_disk_anywhere_in_the_state():
    cfg = CollectConfig(n_starts=96, n_goals=4, chunk_size=96)
    data = collect_arm(jax.random.PRNGKey(3), ARM, cfg, task=LONG, progress=False)
    s, s_next = np.asarray(data.s), np.asarray(data.s_next)
    assert s.shape[1] == s_next.shape[1] == 5 and data.a.shape[1] == 3
    disk, disk_next = s[:, 3:] / LONG.disk_scale, s_next[:, 3:] / LONG.disk_scale
    assert np.abs(disk).max() <= LONG.disk_range + 1e-6
    assert disk.std(0).min() > LONG.disk_range / 3  # spread over the square (uniform: r / sqrt 3)
    # The disk column moves only when the push moved the disk (the reward's input):
    moved = np.linalg.norm(disk_next - disk, axis=1) >= ARM.push.move_threshold
    assert ((np.asarray(data.r) != 0) <= moved).all()
    # Every push starts with the fingertip outside the disk wherever the disk is.
    tip = fingertip_xy(s[:, :3], ARM)
    assert (np.linalg.norm(tip - disk, axis=1) > ARM.contact_distance - ARM.push.finger_radius / 2).all()


def test_arm_long_horizon_task():
    # One compiled task, two policies: "still" (joint moves of zero) and "swing" (joint 1
    # only: the whole arm swings), chosen by a traced flag.
    env = ArmEnv(ARM)
    cfg = EvalConfig(long_rollouts=24, long_max_steps=12, success_radius=0.25, long_finger_box=0.5)
    run = jax.jit(lambda key, swing: arm_protocol_b(
        env, lambda k, s, g: (jnp.tile(jnp.array([1.0, 0.0, 0.0]) * swing, (s.shape[0], 1)),
                              jnp.ones(s.shape[0], bool)), key, cfg, LONG))
    # Still: only rollouts that start at their target succeed (0 steps), none moves.
    ro, target, q = run(jax.random.PRNGKey(1), 0.0)
    disk0, target = np.asarray(ro.disk[0]), np.asarray(target)
    assert np.abs(disk0).max() <= LONG.long_range and np.abs(target).max() <= LONG.long_range
    tip0 = np.asarray(ro.finger[0])
    np.testing.assert_allclose(tip0, np.asarray(fingertip_xy(q[0], ARM)), atol=1e-6)
    assert (np.abs(tip0 - disk0).max(1) <= cfg.long_finger_box).all()
    assert (np.linalg.norm(tip0 - disk0, axis=1) > ARM.contact_distance).all()
    at_target = np.linalg.norm(target - disk0, axis=1) < cfg.success_radius
    assert 0 < at_target.sum() < at_target.size  # the radius makes both kinds likely
    outcome, steps = np.asarray(ro.outcome), np.asarray(ro.steps)
    np.testing.assert_array_equal(outcome, np.where(at_target, CORRECT, NOT_PUSHED))
    np.testing.assert_array_equal(steps, np.where(at_target, 0, cfg.long_max_steps))
    np.testing.assert_array_equal(np.asarray(ro.disk), np.broadcast_to(disk0, ro.disk.shape))
    # Swing: the outcomes are what the disk's final positions say.
    ro, target, _ = run(jax.random.PRNGKey(1), 1.0)
    final, outcome = np.asarray(ro.disk[-1]), np.asarray(ro.outcome)
    assert (np.linalg.norm(final - disk0, axis=1) > 0.01).any()  # some pushes happened
    reached = np.linalg.norm(np.asarray(target) - final, axis=1) < cfg.success_radius
    off = np.abs(final).max(1) > ARM.push.table_half_size
    assert ((outcome == CORRECT) == reached).all() and ((outcome == WRONG) == (off & ~reached)).all()


def _config(cycles: int):
    base = preset("smoke")
    return dataclasses.replace(
        base, collect=CollectConfig(n_starts=120, n_goals=6, chunk_size=120),
        neighbours=NeighbourConfig(k=8),
        train=TrainConfig(cycles=cycles, epochs=1, batch_size=256, width=16, target_batch_size=2048),
        eval=EvalConfig(n_directions=4, episodes_per_direction=2, max_steps=3, long_rollouts=3,
                        long_max_steps=4))


def test_fit_arm_resumes_as_if_never_stopped(tmp_path, monkeypatch):
    run = tmp_path / "arm_long"
    fit_arm(_config(2), run, task=LONG, evaluate=False, progress=False)

    # From here on, collecting stops the run: a resumed run reuses its saved dataset.
    class Collected(Exception):
        pass

    def stub(*args, task, **kwargs):
        raise Collected(task)

    monkeypatch.setattr("lazyq_jax.arm_task.collect_arm", stub)
    with pytest.raises(RunDirError, match="--resume"):
        fit_arm(_config(3), run, task=LONG, progress=False)
    with pytest.raises(RunDirError, match="arm_radius_s"):
        fit_arm(_config(3), run, task=LONG, resume=True, radius_s=0.2, progress=False)
    results = fit_arm(_config(3), run, task=LONG, resume=True, progress=False)
    assert results["protocol_a"]["per_goal"][0]["goal"] == 0.0 and results["protocol_b"]["rollouts"] == 3
    assert json.loads((run / "eval" / "results.json").read_text())["protocol_b"] == results["protocol_b"]
    for fig in ("fig4_outcomes", "fig5_long_horizon", "arm_value", "arm_trajectories"):
        assert (run / "figures" / f"{fig}.png").stat().st_size > 0
    assert [json.loads(x)["cycle"] for x in (run / "metrics.jsonl").read_text().splitlines()] == [1, 2, 3]

    # The same three cycles without a stop, from the saved data and the run's keys.
    config = _config(3)
    data, _, _ = load_dataset(run / "dataset.npz")
    keys = run_keys(config)
    nb = find_neighbours(keys["neighbours"], data.s, data.g, data.s, data.g, k=8, radius_s=0.12,
                         radius_g=config.neighbours.radius_g, growth=config.neighbours.growth)
    trainer = make_train(config.train, ARM.action_length, state_dim=5, goal="angle",
                         state_scale=LONG.state_scale(ARM))
    state = trainer.init(keys["train"])
    for _ in range(3):
        state, _ = jax.jit(trainer.run_cycle)(state, data, nb.idx)
    resumed, _ = load_checkpoint(run / "checkpoints", target=jax.eval_shape(trainer.init, keys["train"]))
    assert int(resumed.cycle) == 3
    jax.tree.map(np.testing.assert_array_equal, resumed.params, state.params)

    # Starting afresh with another disk range must not reuse the saved dataset.
    with pytest.raises(Collected):
        fit_arm(_config(1), run, task=ArmTask(disk_range=0.3), overwrite=True, progress=False)
