"""Local action value models fitted per neighbourhood (paper Eq. 4-6, 9).

``Q(s, a, g) ~ alpha + beta^T a`` is fitted by least squares to the ``k``
neighbours' ``(a_j, y_j)`` (Eq. 5-6), for a whole batch of neighbourhoods at
once, in closed form:

* centre each neighbourhood: ``A = a - mean(a)``, ``y - mean(y)`` (uncentred
  float32 normal equations lose all accuracy on nearly collinear actions);
* solve ``(A^T A + lam I) beta = A^T y`` (explicit 2x2 inverse for ``n_a = 2``,
  batched ``solve`` otherwise); ``alpha = mean(y) - beta . mean(a)``.

``lam = RIDGE * trace(A^T A) / n_a`` (``RIDGE = 1e-5``) is a ridge *relative* to the action
spread (so invariant to the units of ``a``). It changes well-conditioned fits by
~1e-5 relative; on rank-deficient neighbourhoods (collinear actions, fewer than
``n_a + 1`` distinct actions) it gives a solution within ~1% of the minimum-norm
least squares one (float32 rounding of the nearly singular 2x2 system is what
limits it: a smaller ridge would be noisier there), and ``beta = 0,
alpha = mean(y)`` when all actions are equal. Never NaN or inf (for finite input).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

RIDGE = 1e-5
TINY = 1e-30


def _centred(actions, weights):
    """Weighted means and centred actions; weights ``None`` means all ones."""
    if weights is None:
        w = jnp.ones(actions.shape[:-1], actions.dtype)
    else:
        w = jnp.asarray(weights, actions.dtype)
    sw = jnp.maximum(w.sum(-1), TINY)
    a_mean = jnp.einsum("...k,...ka->...a", w, actions) / sw[..., None]
    # A column equal for every counted neighbour (e.g. one move's copies with other goals)
    # is centred to exactly 0: its float32 mean can be off by an ulp (0.1 is not a float),
    # and the normalised system would read that rounding as a direction.
    counted = (w > 0)[..., None]
    equal = (jnp.max(jnp.where(counted, actions, -jnp.inf), axis=-2)
             == jnp.min(jnp.where(counted, actions, jnp.inf), axis=-2))
    return w, sw, a_mean, jnp.where(equal[..., None, :], 0.0, actions - a_mean[..., None, :])


def _regularised_inverse(cov):
    """``(cov + lam I)^-1`` for a batch of PSD ``[n_a, n_a]`` matrices (lam: module docstring).

    Computed as ``inv(cov/s + RIDGE I) / s`` with ``s = trace/n_a`` (``s = 1`` where the
    trace is 0) so that the determinant is well scaled in float32 for any units.
    """
    n_a = cov.shape[-1]
    scale = jnp.trace(cov, axis1=-2, axis2=-1) / n_a
    scale = jnp.where(scale > 0, scale, 1.0)[..., None, None]
    reg = cov / scale + RIDGE * jnp.eye(n_a, dtype=cov.dtype)
    if n_a == 1:
        return 1.0 / (reg * scale)
    if n_a == 2:
        a, b, d = reg[..., 0, 0], reg[..., 0, 1], reg[..., 1, 1]
        det = a * d - b * b
        inv = jnp.stack([jnp.stack([d, -b], -1), jnp.stack([-b, a], -1)], -2)
        return inv / (det[..., None, None] * scale)
    return jnp.linalg.inv(reg) / scale


def fit_local_linear(actions, values, weights=None, offsets=None):
    """Least squares ``values ~ alpha + beta . a`` per neighbourhood (Eq. 5-6).

    Args:
      actions: ``[..., k, n_a]``; values: ``[..., k]``; weights: optional
        ``[..., k]`` non-negative (e.g. a 0/1 mask), weighted least squares.
      offsets: optional ``[..., k, m]``: each neighbour's state offset from the
        neighbourhood's centre (the query).  Then the model is ``values ~ alpha + beta . a
        + gamma . offset``: the neighbours' values differ by where they start as well as
        by their action, and the offset term absorbs the first of these instead of
        letting it bias or blur ``beta`` (a local model in state and action, §IV-A's
        "other local function approximations"); ``alpha`` is the value at the centre.
    Returns:
      ``(alpha [...], beta [..., n_a])``.
    """
    actions = jnp.asarray(actions, jnp.float32)
    values = jnp.asarray(values, jnp.float32)
    if actions.ndim < 2 or values.shape != actions.shape[:-1]:
        raise ValueError(f"need actions [..., k, n_a] and values [..., k]; got {actions.shape}, {values.shape}")
    if offsets is not None:
        return fit_with_offsets(actions, values, weights, offsets)[:2]
    w, sw, a_mean, centred = _centred(actions, weights)
    v_mean = (w * values).sum(-1) / sw
    wa = centred * w[..., None]
    cov = jnp.einsum("...ka,...kb->...ab", wa, centred)
    rhs = jnp.einsum("...ka,...k->...a", wa, values - v_mean[..., None])
    beta = jnp.einsum("...ab,...b->...a", _regularised_inverse(cov), rhs)
    alpha = v_mean - jnp.einsum("...a,...a->...", beta, a_mean)
    return alpha, beta


def fit_with_offsets(actions, values, weights=None, offsets=None):
    """:func:`fit_local_linear`'s fit and each neighbour's value moved to the neighbourhood's
    centre: ``(alpha [...], beta [..., n_a], moved [..., k])`` with ``moved_j = y_j - c .
    offset_j`` (``c``: the fit's offset coefficients), i.e. ``alpha + beta . a_j`` plus the
    neighbour's residual: what its action is worth from the centre's state and goal.
    Without ``offsets``, ``moved = values``."""
    actions = jnp.asarray(actions, jnp.float32)
    values = jnp.asarray(values, jnp.float32)
    if offsets is None:
        alpha, beta = fit_local_linear(actions, values, weights)
        return alpha, beta, values
    offsets = jnp.asarray(offsets, jnp.float32)
    if offsets.shape[:-1] != actions.shape[:-1]:
        raise ValueError(f"offsets [..., k, m] must match actions {actions.shape[:-1]}, got {offsets.shape}")
    n_a = actions.shape[-1]
    alpha, coef = fit_local_linear(jnp.concatenate([actions, offsets], -1), values, weights)
    moved = values - jnp.einsum("...km,...m->...k", offsets, coef[..., n_a:])
    return alpha, coef[..., :n_a], moved


def expectile_loss(adv: jax.Array, diff: jax.Array, expectile: float) -> jax.Array:
    """OGBench's ``expectile_loss`` (GCIVL, GCIQL; IQL's expectile regression, Kostrikov et al.
    2022): ``|tau - 1(adv < 0)| diff^2`` elementwise (the weight ``tau`` where ``adv >= 0``).
    With ``adv = diff = x - v`` its mean over a sample ``x`` is minimised by the
    ``tau``-expectile of ``x`` (:func:`expectile`)."""
    weight = jnp.where(adv >= 0, expectile, 1.0 - expectile)
    return weight * diff ** 2


def expectile(values, tau: float, weights=None):
    """The ``tau``-expectile of ``values [..., k]`` over the last axis (with ``weights [..., k]``
    >= 0, not all 0): the ``m`` with ``tau sum_j w_j (y_j - m)_+ = (1 - tau) sum_j w_j (m - y_j)_+``
    (Newey & Powell 1987; IQL's and GCIVL's expectile, here over a neighbourhood).  ``tau =
    0.5`` is the (weighted) mean, ``tau -> 1`` the maximum.  Exact, by sorting: between two
    consecutive sorted values the equation is linear in ``m``.  Monotone in every value and
    ``m(y + c) = m(y) + c``, so 1-Lipschitz in the max norm.  ``0 < tau < 1``."""
    if not 0.0 < tau < 1.0:
        raise ValueError(f"the expectile's tau must lie in (0, 1), got {tau!r}")
    values = jnp.asarray(values, jnp.float32)
    w = jnp.ones_like(values) if weights is None else jnp.broadcast_to(jnp.asarray(weights, jnp.float32),
                                                                       values.shape)
    order = jnp.argsort(values, axis=-1)
    x = jnp.take_along_axis(values, order, -1)
    w = jnp.take_along_axis(w, order, -1)
    w_below = jnp.cumsum(w, -1)  # weight and weighted sum of x_1..x_i
    s_below = jnp.cumsum(w * x, -1)
    w_all, s_all = w_below[..., -1:], s_below[..., -1:]
    # The equation's left minus right side at m = x_i: decreasing in i, >= 0 where the root is >= x_i.
    f = tau * (s_all - s_below - (w_all - w_below) * x) - (1 - tau) * (w_below * x - s_below)
    i = jnp.clip(jnp.sum(f >= 0, -1, keepdims=True), 1, values.shape[-1]) - 1  # the root in [x_i, x_i+1]
    wb, sb = jnp.take_along_axis(w_below, i, -1), jnp.take_along_axis(s_below, i, -1)
    m = ((1 - tau) * sb + tau * (s_all - sb)) / jnp.maximum((1 - tau) * wb + tau * (w_all - wb), 1e-30)
    lo = jnp.take_along_axis(x, i, -1)
    hi = jnp.take_along_axis(x, jnp.minimum(i + 1, values.shape[-1] - 1), -1)
    return jnp.clip(m, lo, hi)[..., 0]


def goal_offsets(g_nb, g0, angle: bool):
    """Each neighbour's goal offset ``g_j - g``: vectors ``[..., k, d_g]`` / ``[..., d_g]`` give
    ``[..., k, d_g]``; angles (``angle=True``) ``[..., k]`` / ``[...]`` their difference wrapped
    to ``[-pi, pi)``, as one column ``[..., k, 1]``."""
    g_nb, g0 = jnp.asarray(g_nb, jnp.float32), jnp.asarray(g0, jnp.float32)
    if angle:
        d = g_nb - g0[..., None]
        return (jnp.mod(d + jnp.pi, 2 * jnp.pi) - jnp.pi)[..., None]
    return g_nb - g0[..., None, :]


def neighbour_offsets(s_nb, s0, g_nb=None, g0=None):
    """The covariates of the extended local models: each neighbour's state offset ``s_j - s``
    (``s_nb [..., k, d_s]``, ``s0 [..., d_s]``) and, if goals are given, its goal offset
    (:func:`goal_offsets`): ``[..., k, m]`` for :func:`fit_local_linear`'s ``offsets``."""
    parts = [jnp.asarray(s_nb, jnp.float32) - jnp.asarray(s0, jnp.float32)[..., None, :]]
    if g_nb is not None:
        parts.append(goal_offsets(g_nb, g0, angle=jnp.ndim(g_nb) == parts[0].ndim - 1))
    return jnp.concatenate(parts, -1)


def epanechnikov_weights(x_nb, x0, g_nb, g0, level, *, radius_s, radius_g, growth):
    """Weights of a distance-weighted local fit (``neighbours.fit_weights="epanechnikov"``):
    ``(1 - d_s^2 / R_s^2)(1 - d_g^2 / R_g^2)`` per neighbour, ``[..., k]``.

    ``x_nb [..., k, d]`` / ``x0 [..., d]``: the neighbours and the centre in the search space
    (the states or their features); ``g_nb`` / ``g0``: goals as in :func:`neighbour_offsets`
    (angles wrapped) or ``None`` (no goal factor); ``level [...]``: the neighbourhood's growth
    level, so ``R_s = radius_s growth^level`` and ``R_g = radius_g growth^level`` are the
    radii its members were found in (a level below 0, no neighbourhood, counts as 0).
    Members lie strictly inside both balls, so their weights are in ``(0, 1]`` up to
    float32 rounding at the rim (clamped at 0).
    """
    x_nb, x0 = jnp.asarray(x_nb, jnp.float32), jnp.asarray(x0, jnp.float32)
    scale = jnp.float32(growth) ** jnp.maximum(jnp.asarray(level), 0).astype(jnp.float32)
    d_s2 = jnp.sum((x_nb - x0[..., None, :]) ** 2, axis=-1)
    w = jnp.maximum(1.0 - d_s2 / (jnp.float32(radius_s) * scale)[..., None] ** 2, 0.0)
    if g_nb is not None:
        d = goal_offsets(g_nb, g0, angle=jnp.ndim(g_nb) == x_nb.ndim - 1)
        d_g2 = jnp.sum(d * d, axis=-1)
        w = w * jnp.maximum(1.0 - d_g2 / (jnp.float32(radius_g) * scale)[..., None] ** 2, 0.0)
    return w


def precompute_projection(actions, weights=None):
    """Data-only part of :func:`fit_local_linear`: ``P [..., 1 + n_a, k]`` with
    ``[alpha, beta] = P @ values`` (see :func:`apply_projection`).

    Neighbourhoods (hence their actions) do not depend on the network, so ``P``
    can be computed once per dataset.
    """
    actions = jnp.asarray(actions, jnp.float32)
    w, sw, a_mean, centred = _centred(actions, weights)
    wa = centred * w[..., None]
    cov = jnp.einsum("...ka,...kb->...ab", wa, centred)
    p_beta = jnp.einsum("...ab,...kb->...ak", _regularised_inverse(cov), wa)  # [..., n_a, k]
    p_alpha = w / sw[..., None] - jnp.einsum("...a,...ak->...k", a_mean, p_beta)
    return jnp.concatenate([p_alpha[..., None, :], p_beta], axis=-2)


def apply_projection(projection, values):
    """``(alpha, beta)`` from a :func:`precompute_projection` result and ``values [..., k]``."""
    ab = jnp.einsum("...ck,...k->...c", projection, jnp.asarray(values, jnp.float32))
    return ab[..., 0], ab[..., 1:]


def safe_norm(x, axis=-1):
    """``||x||`` with a finite gradient (zero) at ``x = 0``."""
    sq = jnp.sum(x * x, axis=axis)
    pos = sq > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, sq, 1.0)), 0.0)


def greedy_action(beta, action_length, action_set: str = "ball"):
    """Greedy action of the lazy model, Eq. (9): the maximiser of ``beta . a`` over the
    action set: ``c beta / ||beta||`` on the ball ``||a|| <= c`` (``"ball"``, the paper's),
    ``c sign(beta)`` on the box ``|a_i| <= c`` (``"box"``).

    Where the maximiser is not unique the centre is taken: ``beta = 0`` gives the zero
    action (every action equally good), and on the box a component with ``beta_i = 0``
    stays 0 (any value in ``[-c, c]`` is optimal there).  Gradients are finite.
    """
    beta = jnp.asarray(beta, jnp.float32)
    if action_set == "box":
        return action_length * jnp.sign(beta)
    sq = jnp.sum(beta * beta, axis=-1, keepdims=True)
    pos = sq > 0
    return jnp.where(pos, action_length * beta * jax.lax.rsqrt(jnp.where(pos, sq, 1.0)), 0.0)


def boundary_action(key, shape, action_length, action_set: str = "ball"):
    """Actions drawn uniformly from the boundary of the action set, ``[..., n_a]`` of
    ``shape``: a direction uniform on the sphere times ``c`` (``"ball"``), a uniform corner
    ``c (+-1, ..., +-1)`` (``"box"``).  Where Eq. (9)'s argmax is the whole set (``beta = 0``)
    these are the maximisers :func:`greedy_action` would pick for a random ``beta``."""
    if action_set == "box":
        return action_length * jax.random.rademacher(key, shape, jnp.float32)
    d = jax.random.normal(key, shape, jnp.float32)
    return action_length * d / safe_norm(d)[..., None]


def max_linear(beta, action_length, action_set: str = "ball"):
    """``max_a beta . a`` over the action set (Eq. 7's second term): ``c ||beta||`` on the
    ball, ``c sum_i |beta_i|`` on the box."""
    if action_set == "box":
        return action_length * jnp.sum(jnp.abs(jnp.asarray(beta, jnp.float32)), axis=-1)
    return action_length * safe_norm(beta)
