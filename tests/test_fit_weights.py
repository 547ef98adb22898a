"""Distance-weighted local fits (``neighbours.fit_weights="epanechnikov"``): the weights
against NumPy, the weighted fits of training and of the policy against float64 weighted
least squares, the agent's neighbourhoods, and the run guard for runs made before the
option existed."""

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lazyq_jax.agents import lazy
from lazyq_jax.agents.base import Problem
from lazyq_jax.agents.reference import line_task
from lazyq_jax.config import ConfigError, NeighbourConfig, TrainConfig, to_dict
from lazyq_jax.local_model import epanechnikov_weights
from lazyq_jax.neighbours.common import radius_tables
from lazyq_jax.policy import FitKernel, LazyPolicy, lazy_policy, policy_index
from lazyq_jax.run.rundir import RunDirError, open_method, open_run
from lazyq_jax.targets import local_fits
from lazyq_jax.tasks import preset
from lazyq_jax.types import Transitions

R_S, R_G, GROWTH = 0.3, 0.5, 2 ** (1 / 3)


def weights_np(x_nb, x0, g_nb, g0, level, angle):
    """float64 reference: ``(1 - d_s^2/R_s^2)(1 - d_g^2/R_g^2)`` at the level's radii."""
    scale = GROWTH ** np.maximum(level, 0)
    w = 1 - np.sum((x_nb - x0[:, None]) ** 2, -1) / (R_S * scale[:, None]) ** 2
    if g_nb is not None:
        if angle:
            d2 = (np.mod(g_nb - g0[:, None] + np.pi, 2 * np.pi) - np.pi) ** 2
        else:
            d2 = np.sum((g_nb - g0[:, None]) ** 2, -1)
        w = w * (1 - d2 / (R_G * scale[:, None]) ** 2)
    return np.maximum(w, 0)


@pytest.mark.parametrize("goal", [None, "angle", "vector"])
def test_weights_against_numpy(goal):
    """Members inside both balls of their level get weights in (0, 1], 1 at the centre; angle
    goals across +-pi count by their wrapped distance; a level of -1 counts as 0."""
    rng = np.random.default_rng(0)
    n, k, d = 40, 9, 3
    level = rng.integers(-1, 4, n)
    scale = GROWTH ** np.maximum(level, 0)
    x0 = rng.normal(size=(n, d))
    u = rng.normal(size=(n, k, d))
    u /= np.linalg.norm(u, axis=-1, keepdims=True)
    x_nb = x0[:, None] + u * (R_S * scale[:, None, None]) * rng.uniform(0, 1, (n, k, 1))
    x_nb[:, 0] = x0  # a neighbour at the centre
    g_nb = g0 = None
    if goal == "angle":
        g0 = np.full(n, np.pi - 0.05)
        g_nb = np.mod(g0[:, None] + R_G * scale[:, None] * rng.uniform(-1, 1, (n, k)) + np.pi,
                      2 * np.pi) - np.pi  # many wrap to near -pi
        g_nb[:, 0] = g0
    elif goal == "vector":
        g0 = rng.normal(size=(n, 2))
        v = rng.normal(size=(n, k, 2))
        v /= np.linalg.norm(v, axis=-1, keepdims=True)
        g_nb = g0[:, None] + v * (R_G * scale[:, None, None]) * rng.uniform(0, 1, (n, k, 1))
        g_nb[:, 0] = g0
    w = np.asarray(epanechnikov_weights(x_nb, x0, g_nb, g0, level, radius_s=R_S, radius_g=R_G,
                                        growth=GROWTH))
    ref = weights_np(x_nb, x0, g_nb, g0, level, goal == "angle")
    # float32 distances of O(1) coordinates: ~1e-6 relative, divided by R^2 >= 0.09
    np.testing.assert_allclose(w, ref, atol=5e-5)
    assert np.all(w[:, 0] == 1.0) and np.all(w >= 0) and np.all(w <= 1)
    if goal == "angle":
        assert np.mean(g_nb < 0) > 0.2  # the wrap was exercised


def test_weighted_local_fits_against_weighted_lstsq():
    """``local_fits(weights=...)`` (state offsets as covariates) is, per row, the float64
    least squares of ``sqrt(w_j) y_j`` on ``sqrt(w_j) (1, a_j, s_j - s_i)``; uniform weights
    give the unweighted fit (up to rounding); weights and a projection together are refused."""
    rng = np.random.default_rng(1)
    n, k = 50, 14
    s = rng.normal(size=(n, 3)).astype(np.float32)
    data = Transitions(s=jnp.asarray(s), a=jnp.asarray(rng.uniform(-1, 1, (n, 2)), jnp.float32),
                       s_next=jnp.asarray(s + 0.1), r=jnp.asarray(rng.normal(size=n), jnp.float32),
                       g=None, done=jnp.zeros(n, bool))
    idx = rng.integers(0, n, (n, k))
    w = rng.uniform(0.05, 1.0, (n, k)).astype(np.float32)
    v = lambda s_, g_: jnp.sin(jnp.sum(s_, -1))
    alpha, beta, y_nb = local_fits(v, data, jnp.asarray(idx), gamma=0.9, state_offsets=True,
                                   weights=jnp.asarray(w))
    y = np.asarray(y_nb, np.float64)
    a = np.asarray(data.a, np.float64)
    for i in range(n):
        x = np.concatenate([np.ones((k, 1)), a[idx[i]], s[idx[i]] - s[i]], 1)
        sw = np.sqrt(w[i].astype(np.float64))[:, None]
        coef = np.linalg.lstsq(x * sw, y[i] * sw[:, 0], rcond=None)[0]
        scale = np.abs(coef).max() + np.abs(y[i]).max()
        np.testing.assert_allclose(alpha[i], coef[0], atol=2e-3 * scale)
        np.testing.assert_allclose(beta[i], coef[1:3], atol=2e-3 * scale)
    plain = local_fits(v, data, jnp.asarray(idx), gamma=0.9, state_offsets=True)
    ones = local_fits(v, data, jnp.asarray(idx), gamma=0.9, state_offsets=True,
                      weights=jnp.ones((n, k)))
    # Weights of 1 multiply exactly, but the two programs are compiled apart (their fusion and
    # reduction order may differ): equal up to float32 rounding of terms of size ~1.
    np.testing.assert_allclose(np.asarray(ones[1]), np.asarray(plain[1]), rtol=0,
                               atol=1e-5 * (float(np.abs(plain[1]).max()) + 1.0))
    with pytest.raises(ValueError, match="not both"):
        local_fits(v, data, jnp.asarray(idx), gamma=0.9, weights=jnp.asarray(w),
                   projection=jnp.zeros((n, 3, k)))


def test_policy_weighted_fit_against_numpy():
    """With ``k = N`` every query's neighbourhood is the whole dataset, at the smallest level
    whose balls hold it all: the policy's beta is then the float64 weighted least squares
    over all rows with the weights of that level (vector goals, the general query)."""
    rng = np.random.default_rng(2)
    n, d = 24, 3
    s = rng.uniform(-0.1, 0.1, (n, d)).astype(np.float32)
    g = rng.uniform(-0.1, 0.1, (n, 2)).astype(np.float32)
    a = rng.normal(size=(n, d)).astype(np.float32)
    values = rng.normal(size=n).astype(np.float32)
    index = policy_index(s, g, k=n, radius_s=R_S, radius_g=R_G, growth=GROWTH, max_level=4)
    policy = LazyPolicy(index, jnp.asarray(a), jnp.asarray(values), jnp.float32(0.1), "ball",
                        kernel=FitKernel(jnp.asarray(s), jnp.asarray(g), R_S, R_G, GROWTH))
    qs = rng.uniform(-0.15, 0.15, (6, d)).astype(np.float32)
    qg = rng.uniform(-0.15, 0.15, (6, 2)).astype(np.float32)
    _, beta, found = jax.jit(lazy_policy)(policy, jax.random.PRNGKey(0), jnp.asarray(qs), jnp.asarray(qg))
    assert np.all(np.asarray(found))
    r2s, rg = radius_tables(R_S, R_G, GROWTH, np.arange(5))
    for q in range(6):
        d_s2 = np.sum((s - qs[q]) ** 2, -1, dtype=np.float32)
        d_g2 = np.sum((g - qg[q]) ** 2, -1, dtype=np.float32)
        level = next(lv for lv in range(5) if np.all(d_s2 < r2s[lv]) and np.all(d_g2 < rg[lv] ** 2))
        w = weights_np(s[None].astype(np.float64), qs[q][None].astype(np.float64), g[None].astype(np.float64),
                       qg[q][None].astype(np.float64), np.array([level]), False)[0]
        x = np.concatenate([np.ones((n, 1)), a], 1) * np.sqrt(w)[:, None]
        coef = np.linalg.lstsq(x, values * np.sqrt(w), rcond=None)[0]
        np.testing.assert_allclose(np.asarray(beta[q]), coef[1:], atol=2e-3 * np.abs(coef).max())
        unweighted = np.linalg.lstsq(np.concatenate([np.ones((n, 1)), a], 1), values, rcond=None)[0]
        assert np.abs(unweighted[1:] - coef[1:]).max() > 1e-2  # the weights change the fit


def test_agent_neighbourhoods_carry_the_weights_and_uniform_carries_none():
    """``prepare`` with ``fit_weights="epanechnikov"``: the same neighbourhoods as uniform (same
    key) and, per row, the weights of its members at its level; a block trains finite."""
    data = line_task(0, 3000, d=3, goal="vector", band=(0.0, 0.5), n_goals=4)
    n = data.size
    problem = Problem(action_length=0.1)
    nc = NeighbourConfig(k=20, radius_s=0.15, radius_g=0.3, local_model="action+state")
    tc = TrainConfig(cycles=1, epochs=1, batch_size=256, width=8, depth=2)
    uniform = lazy.make(lazy.LazyConfig(train=tc, neighbours=nc), problem)
    weighted = lazy.make(lazy.LazyConfig(train=tc, neighbours=dataclasses.replace(
        nc, fit_weights="epanechnikov")), problem)
    nb_u = uniform.prepare(0, data, n, 0)
    nb_w = weighted.prepare(0, data, n, 0)
    assert nb_u.weights is None
    np.testing.assert_array_equal(np.asarray(nb_u.idx), np.asarray(nb_w.idx))
    s, g, idx, lv = (np.asarray(x, np.float64) for x in (data.s, data.g, nb_w.idx, nb_w.level))
    idx, lv = idx.astype(int), lv.astype(int)
    scale = GROWTH ** lv
    ref = np.maximum(1 - np.sum((s[idx] - s[:, None]) ** 2, -1) / (nc.radius_s * scale[:, None]) ** 2, 0) \
        * np.maximum(1 - np.sum((g[idx] - g[:, None]) ** 2, -1) / (nc.radius_g * scale[:, None]) ** 2, 0)
    np.testing.assert_allclose(np.asarray(nb_w.weights), ref, atol=1e-4)
    assert np.mean(np.asarray(nb_w.weights) > 0) > 0.99
    state = weighted.init(jax.random.PRNGKey(0), data)
    state, metrics = weighted.run_block(state, data, nb_w, n)
    assert np.isfinite(float(metrics["loss"]))
    with pytest.raises(ValueError, match="levels"):
        weighted.train(jax.random.PRNGKey(0), data, aux=nb_w.idx)


def test_config_refuses_unknown_weights():
    with pytest.raises(ConfigError, match="fit_weights"):
        NeighbourConfig(fit_weights="gaussian")


def test_runs_made_before_the_option_resume_at_its_default(tmp_path):
    """A run directory whose stored config and method record lack ``neighbours.fit_weights``
    (made before it existed) resumes with the default, and is refused with another value."""
    config = preset("push", "paper")
    run_dir = tmp_path / "run"
    open_run(run_dir, config, [0], resume=False, overwrite=False)
    stored = json.loads((run_dir / "run.json").read_text())
    del stored["config"]["neighbours"]["fit_weights"]
    (run_dir / "run.json").write_text(json.dumps(stored))
    open_run(run_dir, config, [0], resume=True, overwrite=False)
    (run_dir / "run.json").write_text(json.dumps(stored))
    other = dataclasses.replace(config, neighbours=dataclasses.replace(config.neighbours,
                                                                       fit_weights="epanechnikov"))
    with pytest.raises(RunDirError, match="neighbours.fit_weights"):
        open_run(run_dir, other, [0], resume=True, overwrite=False)

    method_dir = tmp_path / "run" / "lazy"
    method_dir.mkdir()
    defaults = {"neighbours": to_dict(NeighbourConfig())}
    old = {"method": "lazy", "neighbours": {k: v for k, v in to_dict(config.neighbours).items()
                                            if k != "fit_weights"}}
    (method_dir / "method.json").write_text(json.dumps(old))
    open_method(method_dir, {"method": "lazy", "neighbours": to_dict(config.neighbours)}, defaults)
    (method_dir / "method.json").write_text(json.dumps(old))
    with pytest.raises(RunDirError, match="fit_weights"):
        open_method(method_dir, {"method": "lazy", "neighbours": to_dict(other.neighbours)}, defaults)
