"""Benchmark: batched closed-form local least squares (Eq. 5-6) vs NumPy, same run.

1M neighbourhoods of k = 20 actions (n_a = 2). Reports compile and steady-state
time (median, block_until_ready) of ``fit_local_linear``, of the precomputed
projection (``precompute_projection`` once, ``apply_projection`` per cycle) and
of the refit-vs-projection choice inside a target computation (gather
``y[idx]`` + fit), NumPy ``lstsq`` in a loop over a subset (extrapolated), a
vectorised NumPy centred normal-equations version, and the accuracy against
float64 ``lstsq``.

    flock /tmp/lazyq_bench.lock .venv/bin/python experiments/bench_lstsq.py [--n 1000000]
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np
from _common import timed  # the script's own folder is on sys.path

from lazyq_jax.local_model import apply_projection, fit_local_linear, precompute_projection


def numpy_normal_equations(a, v):
    am, vm = a.mean(1), v.mean(1)
    c = a - am[:, None]
    cov = np.einsum("nka,nkb->nab", c, c)
    rhs = np.einsum("nka,nk->na", c, v - vm[:, None])
    beta = np.linalg.solve(cov, rhs[..., None])[..., 0]
    return vm - (beta * am).sum(1), beta


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=1_000_000)
    ap.add_argument("--k", type=int, default=20)
    ap.add_argument("--loop", type=int, default=20_000, help="neighbourhoods for the numpy lstsq loop")
    args = ap.parse_args()
    n, k = args.n, args.k
    rng = np.random.default_rng(0)
    a = rng.uniform(-0.1, 0.1, (n, k, 2)).astype(np.float32)  # actions like the push task's (|a| <= 0.1)
    v = (rng.normal(size=(n, 1)) + a @ rng.normal(size=(2,)) + 0.05 * rng.normal(size=(n, k))).astype(np.float32)
    aj, vj = jnp.asarray(a), jnp.asarray(v)
    print(f"{n:,} neighbourhoods x k={k} x n_a=2, devices={jax.devices()}")

    fit = jax.jit(fit_local_linear)
    (alpha, beta), first, steady = timed(fit, aj, vj, repeats=5)
    print(f"jax fit_local_linear: steady {steady:.3f} s (compile+first {first:.2f} s)")
    proj, first_p, steady_p = timed(jax.jit(precompute_projection), aj, repeats=5)
    print(f"jax precompute_projection (once per dataset): {steady_p:.3f} s (compile+first {first_p:.2f} s)")
    _, _, steady_apply = timed(jax.jit(apply_projection), proj, vj, repeats=5)
    print(f"jax apply_projection (per cycle): {steady_apply:.3f} s")

    # Refit vs projection where it is used: per cycle only y changes; gather y[idx] then fit.
    idx = jnp.asarray(rng.integers(0, n, (n, k)).astype(np.int32))
    y = jnp.asarray(rng.normal(size=n).astype(np.float32))
    a_nb = aj  # the neighbours' actions are fixed per dataset
    _, _, t_refit = timed(jax.jit(lambda y: fit_local_linear(a_nb, y[idx])), y, repeats=5)
    _, _, t_proj = timed(jax.jit(lambda y: apply_projection(proj, y[idx])), y, repeats=5)
    print(f"per-cycle gather y[idx] + refit {t_refit:.3f} s  vs  gather + projection {t_proj:.3f} s")

    m = min(args.loop, n)
    t0 = time.perf_counter()
    ref = np.stack([np.linalg.lstsq(np.column_stack([np.ones(k), a[i].astype(np.float64)]),
                                    v[i].astype(np.float64), rcond=None)[0] for i in range(m)])
    t_loop = (time.perf_counter() - t0) * n / m
    print(f"numpy lstsq loop (float64): {t_loop:.1f} s extrapolated from {m:,}")
    t0 = time.perf_counter()
    _na, nb = numpy_normal_equations(a, v)
    t_np = time.perf_counter() - t0
    print(f"numpy vectorised centred normal equations (float32): {t_np:.3f} s")

    err = lambda x, r: float(np.max(np.abs(x - r)) / np.max(np.abs(r)))
    print(f"max relative error vs float64 lstsq on {m:,}: jax alpha {err(np.asarray(alpha)[:m], ref[:, 0]):.1e}, "
          f"beta {err(np.asarray(beta)[:m], ref[:, 1:]):.1e}; projection beta "
          f"{err(np.asarray(apply_projection(proj, vj)[1])[:m], ref[:, 1:]):.1e}; "
          f"numpy normal eq. beta {err(nb[:m], ref[:, 1:]):.1e}")
    print(f"speed-up of jax fit vs numpy loop {t_loop / steady:.0f}x, vs numpy vectorised {t_np / steady:.1f}x")


if __name__ == "__main__":
    main()
