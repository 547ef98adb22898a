"""Training (§IV-E) on the session's push run and on tasks that are not the push: loss, value,
the clip of Eq. (8), DQN against Double DQN, sizes from the data, checkpoints."""


import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import linen as nn

from lazyq_jax.config import TrainConfig
from lazyq_jax.neighbours import find_neighbours
from lazyq_jax.networks import encode
from lazyq_jax.train import make_train
from lazyq_jax.types import Transitions



def tree_equal(a, b):
    return all(jax.tree.leaves(jax.tree.map(lambda x, y: bool(np.array_equal(x, y)), a, b)))


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


class _PlainValueNetwork(nn.Module):
    """The value network as flax's defaults build it (a zero-initialised output bias): the
    reference for ``value_init = 0``."""

    width: int
    depth: int

    @nn.compact
    def __call__(self, s, g=None, train=False):
        x = encode(s, g)
        for _ in range(self.depth - 1):
            x = nn.relu(nn.BatchNorm(use_running_average=not train, momentum=0.99)(
                nn.Dense(self.width, use_bias=False)(x)))
        return nn.Dense(1)(x)[..., 0]


def test_value_init_moves_only_the_output_bias():
    """``value_init`` starts V there: the last bias is that number, every other parameter is
    the default's (same key), and V is the default's V shifted by it.  The default (0) builds
    bitwise flax's plain network, so the paper's runs are unchanged."""
    data, _ = point_task(n=256, d=2, goal="angle")
    key = jax.random.PRNGKey(3)
    base = make_train(TrainConfig(width=16, depth=4), 0.1)
    low = make_train(TrainConfig(width=16, depth=4, value_init=-100.0), 0.1)
    s0, s1 = base.init(key, data), low.init(key, data)
    reference = _PlainValueNetwork(16, 4).init(jax.random.split(key)[1], data.s[:1], data.g[:1])
    assert tree_equal(s0.params, reference["params"])
    last = "Dense_3"  # depth 4: Dense_0..Dense_3
    assert float(s1.params[last]["bias"][0]) == -100.0
    s1_rest = dict(s1.params, **{last: {"kernel": s1.params[last]["kernel"],
                                        "bias": s0.params[last]["bias"]}})
    assert tree_equal(s1_rest, s0.params)
    v0, v1 = base.value_fn(s0)(data.s, data.g), low.value_fn(s1)(data.s, data.g)
    # |v0| is a few units: the shift's rounding is a few ulps of 100 (7.6e-6 each).
    np.testing.assert_allclose(np.asarray(v1), np.asarray(v0) - 100.0, rtol=0, atol=1e-4)
    with pytest.raises(ValueError, match="value_init must be a finite number"):
        TrainConfig(value_init=float("nan"))


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
