"""Closed-form local least squares (Eq. 5-6) against float64 numpy.linalg.lstsq; greedy action (Eq. 9)."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import brentq

from lazyq_jax.local_model import (
    RIDGE,
    apply_projection,
    expectile,
    fit_local_linear,
    fit_with_offsets,
    greedy_action,
    max_linear,
    neighbour_offsets,
    precompute_projection,
    safe_norm,
)


def lstsq(a, v):
    """float64 reference, one problem at a time: returns (alpha, beta)."""
    a = np.asarray(a, np.float64).reshape(-1, *a.shape[-2:])
    v = np.asarray(v, np.float64).reshape(-1, v.shape[-1])
    sol = np.stack([np.linalg.lstsq(np.column_stack([np.ones(len(x)), x]), y, rcond=None)[0]
                    for x, y in zip(a, v)])
    return sol[:, 0], sol[:, 1:]


def test_matches_lstsq_on_well_conditioned_batches():
    rng = np.random.default_rng(0)
    a = rng.uniform(-0.1, 0.1, (3, 4, 20, 2)).astype(np.float32)
    v = (0.3 + a @ np.array([2.0, -1.0]) + 0.05 * rng.normal(size=(3, 4, 20))).astype(np.float32)
    alpha, beta = fit_local_linear(a, v)
    chex.assert_shape((alpha, beta), ((3, 4), (3, 4, 2)))
    ra, rb = lstsq(a, v)
    np.testing.assert_allclose(np.asarray(alpha).ravel(), ra, rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(np.asarray(beta).reshape(-1, 2), rb, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("n_a, k", [(1, 12), (3, 12), (7, 30)])
def test_general_n_a_uses_batched_solve(n_a, k):
    rng = np.random.default_rng(n_a)
    a = rng.normal(size=(50, k, n_a)).astype(np.float32)
    v = rng.normal(size=(50, k)).astype(np.float32)
    alpha, beta = fit_local_linear(a, v)
    ra, rb = ridge_reference(a, v)
    np.testing.assert_allclose(alpha, ra, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(beta, rb, rtol=1e-4, atol=1e-5)
    _la, lb = lstsq(a, v)  # the ridge (1e-5 of the trace) moves these 12-point fits by < 1e-3
    np.testing.assert_allclose(beta, lb, rtol=1e-3, atol=1e-4)


def test_centring_keeps_accuracy_far_from_the_origin():
    """Actions offset by 100 with spread 0.01: uncentred float32 normal equations fail here."""
    rng = np.random.default_rng(2)
    a = (100.0 + 0.01 * rng.normal(size=(200, 20, 2))).astype(np.float32)
    v = (1.0 + (a - 100.0) @ np.array([3.0, 1.0]) + 1e-3 * rng.normal(size=(200, 20))).astype(np.float32)
    _, beta = fit_local_linear(a, v)
    _, rb = lstsq(a, v)
    np.testing.assert_allclose(beta, rb, rtol=2e-3, atol=2e-3)


def ridge_reference(a, v, ridge=RIDGE):
    """float64 solution of the documented ridge system ``(A^T A + lam I) beta = A^T y``."""
    a = np.asarray(a, np.float64)
    v = np.asarray(v, np.float64)
    am, vm = a.mean(-2), v.mean(-1)
    c = a - am[..., None, :]
    cov = np.einsum("...ka,...kb->...ab", c, c)
    lam = ridge * np.trace(cov, axis1=-2, axis2=-1) / a.shape[-1]
    beta = np.linalg.solve(cov + lam[..., None, None] * np.eye(a.shape[-1]),
                           np.einsum("...ka,...k->...a", c, v - vm[..., None])[..., None])[..., 0]
    return vm - np.einsum("...a,...a->...", beta, am), beta


def test_nearly_collinear_actions_follow_the_ridge_reference():
    rng = np.random.default_rng(3)
    t = rng.uniform(-0.1, 0.1, (100, 20, 1))
    a = (np.concatenate([t, t], -1) + 1e-4 * rng.normal(size=(100, 20, 2))).astype(np.float32)
    v = (2.0 * t[..., 0] + 0.01 * rng.normal(size=(100, 20))).astype(np.float32)
    alpha, beta = fit_local_linear(a, v)
    assert np.isfinite(beta).all()
    ra, rb = ridge_reference(a, v)
    fitted = np.asarray(alpha)[:, None] + np.einsum("nka,na->nk", a, beta)
    ref = ra[:, None] + np.einsum("nka,na->nk", a.astype(np.float64), rb)
    np.testing.assert_allclose(fitted, ref, atol=5e-3)  # float32 on a cond ~1e5 system
    # Along the well-determined direction (1, 1) beta matches the reference closely.
    np.testing.assert_allclose(np.asarray(beta).sum(1), rb.sum(1), rtol=1e-2)


def test_degenerate_neighbourhoods_are_finite_with_ridge_behaviour():
    v = np.arange(20, dtype=np.float32)
    same = np.ones((20, 2), np.float32)  # all actions equal
    alpha, beta = fit_local_linear(same, v)
    np.testing.assert_allclose(beta, 0.0)
    np.testing.assert_allclose(alpha, v.mean())
    # Equal actions whose float32 mean rounds (0.1 is not a float): still exactly beta = 0,
    # weighted or not, and with state offsets beside them (the offsets' coefficients fitted).
    for k in (3, 7, 20, 33):
        tenth = np.tile(np.float32([0.1, -0.3]), (k, 1))
        vk = np.random.default_rng(k).normal(size=k).astype(np.float32)
        np.testing.assert_array_equal(fit_local_linear(tenth, vk)[1], 0.0)
        wk = np.random.default_rng(k + 1).uniform(0.1, 1, k).astype(np.float32)
        np.testing.assert_array_equal(fit_local_linear(tenth, vk, wk)[1], 0.0)
        off = np.random.default_rng(k + 2).normal(size=(k, 2)).astype(np.float32)
        np.testing.assert_array_equal(fit_local_linear(tenth, vk, offsets=off)[1], 0.0)
        np.testing.assert_array_equal(np.asarray(precompute_projection(tenth))[1:], 0.0)
    # Two distinct actions (rank 1): within ~1% of the minimum-norm lstsq solution.
    two = np.where(np.arange(20)[:, None] < 10, [[0.0, 0.0]], [[0.1, 0.1]]).astype(np.float32)
    v2 = np.where(np.arange(20) < 10, 1.0, 2.0).astype(np.float32)
    alpha2, beta2 = fit_local_linear(two, v2)
    ra, rb = lstsq(two, v2)
    np.testing.assert_allclose(beta2, rb[0], rtol=2e-2)
    np.testing.assert_allclose(alpha2, ra[0], rtol=1e-2)
    np.testing.assert_allclose(alpha2 + two @ np.asarray(beta2), v2, atol=2e-2)
    # A single point per neighbourhood, zero weights everywhere: finite as well.
    a0, b0 = fit_local_linear(np.ones((1, 1, 2)), np.ones((1, 1)))
    a1, b1 = fit_local_linear(np.ones((1, 3, 2)), np.ones((1, 3)), weights=np.zeros((1, 3)))
    assert np.isfinite([a0, a1]).all() and np.isfinite(b0).all() and np.isfinite(b1).all()


def test_ridge_is_invariant_to_action_units():
    rng = np.random.default_rng(4)
    a = rng.normal(size=(30, 20, 2)).astype(np.float32)
    v = rng.normal(size=(30, 20)).astype(np.float32)
    alpha, beta = fit_local_linear(a, v)
    alpha_s, beta_s = fit_local_linear(1e-3 * a, v)
    np.testing.assert_allclose(alpha_s, alpha, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(1e-3 * np.asarray(beta_s), beta, rtol=1e-3, atol=1e-5)


def test_weights_mask_equals_fit_on_the_subset():
    rng = np.random.default_rng(5)
    a = rng.normal(size=(10, 20, 2)).astype(np.float32)
    v = rng.normal(size=(10, 20)).astype(np.float32)
    mask = np.arange(20) < 13
    alpha, beta = fit_local_linear(a, v, weights=np.broadcast_to(mask, (10, 20)).astype(np.float32))
    ra, rb = fit_local_linear(a[:, :13], v[:, :13])
    np.testing.assert_allclose(alpha, ra, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(beta, rb, rtol=1e-5, atol=1e-6)


def test_projection_equals_fit_and_jit_equals_eager():
    rng = np.random.default_rng(6)
    a = rng.normal(size=(40, 20, 2)).astype(np.float32)
    v = rng.normal(size=(40, 20)).astype(np.float32)
    alpha, beta = fit_local_linear(a, v)
    proj = precompute_projection(a)
    chex.assert_shape(proj, (40, 3, 20))
    pa, pb = apply_projection(proj, v)
    np.testing.assert_allclose(pa, alpha, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(pb, beta, rtol=1e-5, atol=1e-6)
    ja, jb = jax.jit(fit_local_linear)(a, v)
    np.testing.assert_allclose(ja, alpha, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(jb, beta, rtol=1e-6, atol=1e-7)


def test_greedy_action_direction_length_and_zero_beta():
    beta = jnp.array([[3.0, 4.0], [0.0, 0.0], [1e-30, 0.0]])
    act = greedy_action(beta, 0.1)
    np.testing.assert_allclose(act[0], [0.06, 0.08], rtol=1e-6)
    np.testing.assert_array_equal(act[1], [0.0, 0.0])  # documented: zero beta -> zero action
    assert np.isfinite(act).all()
    grad = jax.grad(lambda b: greedy_action(b, 0.1).sum() + safe_norm(b).sum())(beta)
    assert np.isfinite(grad).all()
    np.testing.assert_allclose(jax.jit(greedy_action, static_argnums=1)(beta, 0.1), act)


@pytest.mark.parametrize("action_set", ["ball", "box"])
def test_greedy_action_and_max_against_a_grid_of_actions(action_set):
    """Eq. (7)'s max and Eq. (9)'s argmax over the action set against brute force: the best of
    a dense grid of actions (the ball's boundary or the box) within the grid's spacing."""
    rng = np.random.default_rng(5)
    c = 0.2
    beta = rng.normal(size=(50, 2)).astype(np.float32)
    beta[:5, 1] = 0.0  # on the box a zero component stays at the centre (any value is optimal)
    if action_set == "ball":
        theta = np.linspace(-np.pi, np.pi, 20001)
        grid = c * np.stack([np.cos(theta), np.sin(theta)], -1)
    else:
        x = np.linspace(-c, c, 401)
        grid = np.stack(np.meshgrid(x, x), -1).reshape(-1, 2)
    best = (beta @ grid.T).max(axis=1)
    np.testing.assert_allclose(max_linear(beta, c, action_set), best, rtol=1e-4, atol=1e-6)
    a = np.asarray(greedy_action(beta, c, action_set))
    np.testing.assert_allclose(np.sum(beta * a, axis=1), best, rtol=1e-4, atol=1e-6)
    if action_set == "box":
        assert np.all(np.isin(a, np.float32([-c, 0.0, c]))) and np.all(a[:5, 1] == 0.0)
    else:
        np.testing.assert_allclose(np.linalg.norm(a, axis=1), c, rtol=1e-6)


def test_state_offsets_as_covariates_match_lstsq():
    """With each neighbour's state offset as a covariate the fit is the least squares of
    ``alpha + beta . a + gamma . offset`` (lstsq on the joint regressors); values that
    depend on the offsets bias the action-only fit's beta but not this one's."""
    rng = np.random.default_rng(3)
    a = rng.uniform(-0.12, 0.12, (50, 20, 3)).astype(np.float32)
    d = rng.uniform(-0.12, 0.12, (50, 20, 3)).astype(np.float32)
    beta, gamma = rng.normal(size=(50, 3)), rng.normal(size=(50, 3))
    v = (0.5 + np.einsum("nka,na->nk", a, beta) + np.einsum("nka,na->nk", d, gamma)
         + 1e-3 * rng.normal(size=(50, 20))).astype(np.float32)
    alpha_ref, coef_ref = lstsq(np.concatenate([a, d], -1), v)
    alpha, b = fit_local_linear(a, v, offsets=d)
    np.testing.assert_allclose(alpha, alpha_ref, atol=1e-4)
    np.testing.assert_allclose(b, coef_ref[:, :3], atol=1e-3 * np.abs(coef_ref).max())
    _, b_plain = fit_local_linear(a, v)
    assert np.abs(b_plain - beta).max() > 10 * np.abs(b - beta).max()
    with pytest.raises(ValueError, match="offsets"):
        fit_local_linear(a, v, offsets=d[:, :5])


@pytest.mark.parametrize("goal", ["vector", "angle"])
def test_goal_offsets_are_the_wrapped_differences(goal):
    """``neighbour_offsets``: ``s_j - s`` then ``g_j - g`` (angles wrapped to [-pi, pi): a
    neighbour at 3.1 of a centre at -3.1 is 0.083 away, not -6.2), against NumPy; and a value
    that moves with the goal offset no longer biases beta once the goal is a covariate."""
    rng = np.random.default_rng(4)
    s_nb, s0 = rng.normal(size=(30, 12, 2)), rng.normal(size=(30, 2))
    if goal == "vector":
        g_nb, g0 = rng.normal(size=(30, 12, 2)), rng.normal(size=(30, 2))
        dg = g_nb - g0[:, None]
    else:
        g0 = rng.uniform(-np.pi, np.pi, 30)
        g_nb = np.mod(g0[:, None] + rng.uniform(-0.3, 0.3, (30, 12)) + np.pi, 2 * np.pi) - np.pi
        g0[0], g_nb[0, 0] = -3.1, 3.1
        dg = (np.mod(g_nb - g0[:, None] + np.pi, 2 * np.pi) - np.pi)[..., None]
        assert abs(dg[0, 0, 0] - (6.2 - 2 * np.pi)) < 1e-12
    off = np.asarray(neighbour_offsets(s_nb, s0, g_nb, g0))
    ref = np.concatenate([s_nb - s0[:, None], dg], -1)
    np.testing.assert_allclose(off, ref, atol=1e-5)
    np.testing.assert_allclose(np.asarray(neighbour_offsets(s_nb, s0)), ref[..., :2], atol=1e-6)
    # values = 1 + beta.a + 5 * first goal offset: the action-only fit is biased, this one not
    a = rng.uniform(-1, 1, (30, 12, 2))
    beta = rng.normal(size=(30, 2))
    # goal offsets correlated with the actions: the action-only fit absorbs them into beta
    if goal == "vector":
        g_nb = g0[:, None] + 0.5 * a + 0.5 * rng.normal(size=a.shape)
        dg = g_nb - g0[:, None]
    v = 1 + np.einsum("nka,na->nk", a, beta) + 5 * dg[..., 0]
    _, b = fit_local_linear(a, v, offsets=neighbour_offsets(s_nb, s0, g_nb, g0))
    _, b_plain = fit_local_linear(a, v, offsets=neighbour_offsets(s_nb, s0))
    # float32 normal equations of 5 covariates with coefficients up to 5: 1e-3 of that
    np.testing.assert_allclose(b, beta, atol=5e-3)
    if goal == "vector":
        assert np.abs(b_plain - beta).max() > 1.0


def test_fit_with_offsets_moves_each_value_to_the_centre():
    """``fit_with_offsets``: the same ``alpha, beta`` as ``fit_local_linear(offsets=...)``, and
    ``moved_j = y_j - c . offset_j`` with ``c`` the offset part of the joint least squares
    (float64 lstsq), i.e. ``alpha + beta . a_j`` plus the neighbour's residual.  Without
    offsets ``moved`` is the values themselves."""
    rng = np.random.default_rng(5)
    a = rng.uniform(-1, 1, (40, 15, 2)).astype(np.float32)
    d = rng.normal(size=(40, 15, 3)).astype(np.float32)
    v = (2.0 + a @ np.array([1.0, -0.5]) + 3.0 * d[..., 0] + 0.3 * rng.normal(size=(40, 15))).astype(np.float32)
    alpha, beta, moved = fit_with_offsets(a, v, offsets=d)
    alpha_plain, beta_plain = fit_local_linear(a, v, offsets=d)
    np.testing.assert_array_equal(alpha, alpha_plain)
    np.testing.assert_array_equal(beta, beta_plain)
    alpha_ref, coef_ref = lstsq(np.concatenate([a, d], -1), v)
    moved_ref = v - np.einsum("nkm,nm->nk", d.astype(np.float64), coef_ref[:, 2:])
    scale = np.abs(v).max()
    np.testing.assert_allclose(moved, moved_ref, atol=1e-4 * scale)
    resid = v - alpha_ref[:, None] - np.einsum("nka,na->nk", a.astype(np.float64), coef_ref[:, :2]) \
        - np.einsum("nkm,nm->nk", d.astype(np.float64), coef_ref[:, 2:])
    np.testing.assert_allclose(moved, alpha_ref[:, None] + np.einsum("nka,na->nk", a, coef_ref[:, :2]) + resid,
                               atol=1e-4 * scale)
    _, _, same = fit_with_offsets(a, v)
    np.testing.assert_array_equal(same, v)
    with pytest.raises(ValueError, match="offsets"):
        fit_with_offsets(a, v, offsets=d[:, :5])


def _expectile_root(y, w, tau):
    """float64 root of ``tau sum w (y - m)_+ = (1 - tau) sum w (m - y)_+`` by Brent's method."""
    if y.min() == y.max():
        return float(y[0])
    f = lambda m: tau * np.sum(w * np.maximum(y - m, 0)) - (1 - tau) * np.sum(w * np.maximum(m - y, 0))
    return brentq(f, y.min(), y.max(), xtol=1e-14, rtol=1e-15)


@pytest.mark.parametrize("tau", [0.1, 0.5, 0.9, 0.99])
def test_expectile_against_root_finding(tau):
    """``expectile`` over the last axis against a float64 root of its defining equation, with
    and without weights, for neighbourhoods of 1-25 values at scales 1e-3 to 1e2 and with
    ties; 0.5 is the (weighted) mean.  float32 sums of <= 25 values: 1e-5 of the scale."""
    rng = np.random.default_rng(int(tau * 100))
    for _ in range(60):
        k = int(rng.integers(1, 26))
        y = rng.normal(size=k) * rng.choice([1e-3, 1.0, 100.0])
        if rng.random() < 0.3:
            y = np.round(y)  # ties
        w = rng.uniform(0.1, 1.0, k)
        y32, w32 = y.astype(np.float32), w.astype(np.float32)
        tol = 1e-5 * max(np.abs(y).max(), 1e-3)
        got = float(expectile(jnp.asarray(y32), tau, jnp.asarray(w32)))
        assert abs(got - _expectile_root(y32.astype(np.float64), w32.astype(np.float64), tau)) <= tol
        got = float(expectile(jnp.asarray(y32), tau))
        assert abs(got - _expectile_root(y32.astype(np.float64), np.ones(k), tau)) <= tol
    y = rng.normal(size=(7, 9)).astype(np.float32)
    w = rng.uniform(0.1, 1.0, (7, 9)).astype(np.float32)
    np.testing.assert_allclose(expectile(y, 0.5, w), (w * y).sum(1) / w.sum(1), atol=1e-6)


def test_expectile_is_monotone_and_shifts_with_the_values():
    """The properties that make an expectile target 1-Lipschitz in the max norm: adding c to
    every value adds c; raising one value never lowers it; so ``|m(y + e) - m(y)| <=
    max |e|``.  And ``tau -> 1`` tends to the maximum, ``tau -> 0`` to the minimum."""
    rng = np.random.default_rng(11)
    y = rng.normal(size=(200, 20)).astype(np.float32)
    e = rng.uniform(-0.5, 0.5, (200, 20)).astype(np.float32)
    m = np.asarray(expectile(y, 0.9))
    np.testing.assert_allclose(expectile(y + 3.0, 0.9), m + 3.0, atol=1e-5)
    up = y.copy()
    up[:, 0] += np.abs(e[:, 0])
    assert np.all(np.asarray(expectile(up, 0.9)) >= m - 1e-6)
    assert np.all(np.abs(np.asarray(expectile(y + e, 0.9)) - m) <= np.abs(e).max(1) + 1e-5)
    assert np.all(np.asarray(expectile(y, 0.999)) <= y.max(1) + 1e-6)
    np.testing.assert_allclose(expectile(y, 0.999999), y.max(1), atol=2e-3)
    np.testing.assert_allclose(expectile(y, 1e-6), y.min(1), atol=2e-3)
    for tau in (0.0, 1.0, 1.5):
        with pytest.raises(ValueError, match="tau"):
            expectile(y, tau)
