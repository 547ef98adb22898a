"""The ablations of lazy Q's value iteration towards GCIVL's (docs/pointmaze.md): without the
lazy model in the targets (``train.target_max="next"``: each row's own one-step target), the
expectile regression (``train.loss_expectile``) and OGBench's LayerNorm blocks
(``train.norm="layer"``): against NumPy's backup, the closed-form expectile and a NumPy
forward pass; the three together through the CLI."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import pointmaze_round_trip
from test_gc_agents import np_mlp

from lazyq_jax.config import ConfigError, TrainConfig
from lazyq_jax.networks import ValueNetwork, encode
from lazyq_jax.train import make_train
from lazyq_jax.types import Transitions


def random_rows(n, seed, all_done=False):
    rng = np.random.default_rng(seed)
    s = rng.uniform(-1, 1, (n, 2)).astype(np.float32)
    a = rng.uniform(-0.1, 0.1, (n, 2)).astype(np.float32)
    g = rng.uniform(-1, 1, (n, 2)).astype(np.float32)
    r = (rng.uniform(size=n) < 0.3).astype(np.float32)  # independent of s and g
    done = np.ones(n, bool) if all_done else r > 0
    return Transitions(s=jnp.asarray(s), a=jnp.asarray(a), s_next=jnp.asarray(s + a),
                       r=jnp.asarray(r), g=jnp.asarray(g), done=jnp.asarray(done))


def test_next_target_is_each_rows_own_one_step_backup():
    """The cycle's targets are ``r + gamma (1 - done) V(s', g)`` of the frozen network (their
    mean and spread, against NumPy), and the neighbourhoods play no part in them."""
    data = random_rows(512, seed=0)
    cfg = TrainConfig(target_max="next", cycles=1, epochs=1, width=8, depth=3, batch_size=64,
                      gamma=0.9)
    trainer = make_train(cfg, 0.1, action_set="box")
    state = trainer.init(jax.random.PRNGKey(0), data)
    v_next = np.asarray(trainer.value_fn(state)(data.s_next, data.g), np.float64)
    y = np.asarray(data.r, np.float64) + 0.9 * np.where(np.asarray(data.done), 0.0, v_next)
    run = jax.jit(trainer.run_cycle)
    idx_a = jnp.zeros((512, 4), jnp.int32)
    idx_b = jax.random.randint(jax.random.PRNGKey(1), (512, 4), 0, 512)
    new_a, metrics = run(state, data, idx_a)
    new_b, _ = run(state, data, idx_b)
    # float32 sums over 512 values of magnitude ~1: a few 1e-7 relative
    np.testing.assert_allclose(float(metrics["target_mean"]), y.mean(), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(float(metrics["target_std"]), y.std(), rtol=1e-4, atol=1e-6)
    assert float(metrics["clip_fraction"]) == 0.0 and "beta_norm_mean" not in metrics
    for x, z in zip(jax.tree.leaves(new_a.params), jax.tree.leaves(new_b.params), strict=True):
        np.testing.assert_array_equal(x, z)


def sample_expectile(x, tau):
    """The ``tau``-expectile ``e`` of a 0/1 sample in closed form: ``tau p (1 - e) = (1 - tau)
    (1 - p) e`` with ``p`` the fraction of ones."""
    p = float(np.mean(x))
    return tau * p / (tau * p + (1 - tau) * (1 - p))


@pytest.mark.parametrize("tau", [0.5, 0.9])
def test_loss_expectile_fits_the_targets_expectile(tau):
    """Targets independent of the state (every row terminal, ``y = r`` in {0, 1}, 30 % ones):
    the best V is the same number everywhere, the targets' mean with the squared error (0.5)
    and their ``tau``-expectile with the expectile regression (~0.79 at 0.9); a small network
    cannot memorise 2048 random rows, so its mean value lands near that number."""
    data = random_rows(2048, seed=1, all_done=True)
    cfg = TrainConfig(target_max="next", loss_expectile=tau, cycles=1, epochs=60, width=8,
                      depth=3, batch_size=256, learning_rate=1e-2, gamma=0.9)
    trainer = make_train(cfg, 0.1, action_set="box")
    state, _ = jax.jit(trainer.train)(jax.random.PRNGKey(0), data, jnp.zeros((2048, 4), jnp.int32))
    v = np.asarray(trainer.value_fn(state)(data.s, data.g))
    want = sample_expectile(np.asarray(data.r), tau)
    other = sample_expectile(np.asarray(data.r), 1.4 - tau)  # 0.5 <-> 0.9
    assert abs(v.mean() - want) < 0.05, (v.mean(), want)
    assert abs(v.mean() - other) > 0.4, (v.mean(), other)  # the two optima are 0.49 apart


@pytest.mark.parametrize("kwargs, match", [
    ({"loss_expectile": 0.0}, "loss_expectile must lie strictly between 0 and 1"),
    ({"loss_expectile": 1.0}, "loss_expectile must lie strictly between 0 and 1"),
    ({"loss_expectile": True}, "loss_expectile must lie strictly between 0 and 1"),
    ({"target_max": "own"}, "target_max must be 'set'.*'next'"),
    ({"target_max": "next", "bootstrap_goal": "row"}, "target_max='next' uses no neighbours"),
    ({"norm": "group"}, "norm must be 'batch'.*or 'layer'"),
])
def test_config_errors(kwargs, match):
    with pytest.raises(ConfigError, match=match):
        TrainConfig(**kwargs)


def test_layer_norm_network_is_ogbenchs_mlp():
    """``norm="layer"``: (Dense, GELU, LayerNorm) x (depth - 1), Dense, on the encoded input,
    against NumPy in float64 (float32 layers of width 16: errors of a few 1e-7), with no batch
    statistics; the trainer's state then carries none and trains."""
    net = ValueNetwork(width=16, depth=3, norm="layer", state_scale=2.0)
    data = random_rows(64, seed=2)
    variables = net.init(jax.random.PRNGKey(0), data.s[:1], data.g[:1])
    assert set(variables) == {"params"}
    x = np.asarray(encode(data.s, data.g, 2.0), np.float64)
    want = np_mlp(jax.tree.map(lambda a: np.asarray(a, np.float64), variables), x, True)[:, 0]
    got = np.asarray(net.apply(variables, data.s, data.g))
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5)
    trainer = make_train(TrainConfig(norm="layer", cycles=2, epochs=2, width=8, depth=3,
                                     batch_size=16), 0.1, action_set="box")
    state, metrics = jax.jit(trainer.train)(jax.random.PRNGKey(0), data,
                                           jnp.zeros((64, 4), jnp.int32))
    assert state.batch_stats == {} and np.all(np.isfinite(np.asarray(metrics["loss"])))


def test_the_ablations_through_the_cli(tmp_path):
    """The whole pointmaze task at smoke scale with all three, multi-step targets
    (``train.target_steps``, tests/test_multi_step.py) and the distance head
    (``train.value_head``, tests/test_distance_head.py): trained, checkpointed, evaluated
    again to the same outcome, reloaded and acting."""
    pointmaze_round_trip(tmp_path / "ablation", "train.target_max=next", "train.loss_expectile=0.9",
                         "train.norm=layer", "train.target_steps=3", "train.value_head=distance")
