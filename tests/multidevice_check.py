"""Checks that need several devices; run by tests/test_parallel.py in its own process.

``XLA_FLAGS=--xla_force_host_platform_device_count=4`` must be set before JAX starts,
so this is a script, not a pytest module.  Every check compares the sharded result
with the single-device one (``mesh=None``, no sharding at all); it prints one line
per check and exits non-zero on the first failure.
"""

import os
import sys
import tempfile

assert "--xla_force_host_platform_device_count=4" in os.environ.get("XLA_FLAGS", ""), \
    "run with XLA_FLAGS=--xla_force_host_platform_device_count=4"

import jax  # noqa: E402
import numpy as np  # noqa: E402

from lazyq_jax.checkpoint import load_checkpoint, save_checkpoint  # noqa: E402
from lazyq_jax.config import (CollectConfig, Config, ConfigError, ParallelConfig,  # noqa: E402
                              TrainConfig)
from lazyq_jax.data import collect  # noqa: E402
from lazyq_jax.neighbours import build_index, search_all  # noqa: E402
from lazyq_jax.parallel import make_mesh, put, replicated  # noqa: E402
from lazyq_jax.targets import local_fits  # noqa: E402
from lazyq_jax.train import make_train  # noqa: E402

assert jax.device_count() == 4, jax.devices()
MESHES = {n: make_mesh(n) for n in (1, 2, 4)}


def leaves(tree):
    return [np.asarray(x) for x in jax.tree.leaves(tree)]


def check_collect_bitwise():
    # 6 chunks of 15 episodes: 4 devices get an uneven last call (padding).
    cfg = CollectConfig(n_starts=90, n_goals=5, chunk_size=16, start_range=0.6)
    ref = collect(jax.random.PRNGKey(7), cfg, progress=False)
    for n in (2, 4):
        out = collect(jax.random.PRNGKey(7), cfg, mesh=MESHES[n], progress=False)
        for a, b in zip(leaves(ref), leaves(out)):
            np.testing.assert_array_equal(a, b, err_msg=f"collect on {n} devices")
    assert int(np.asarray(ref.done).sum()) > 0, "no push moved the disk: the check is too weak"
    print(f"collect: {ref.size} rows bitwise equal on 1 (no mesh), 2 and 4 devices")
    return ref


def check_search_bitwise():
    rng = np.random.default_rng(0)
    s = rng.uniform(-1, 1, (3001, 2)).astype(np.float32)
    s[:300] *= 4  # sparse points that need several growth passes
    g = rng.uniform(-np.pi, np.pi, 3001).astype(np.float32)
    index = build_index(s, g, k=12, max_level=0)
    ref = search_all(index, jax.random.PRNGKey(1), s, g)
    assert int(np.asarray(ref.level).max()) >= 3, "no query grew: the check is too weak"
    for n in (1, 2, 4):
        out = search_all(index, jax.random.PRNGKey(1), s, g, mesh=MESHES[n])
        for a, b in zip(leaves(ref), leaves(out)):
            np.testing.assert_array_equal(a, b, err_msg=f"search on {n} devices")
    print("search: 3001 queries (levels up to "
          f"{int(np.asarray(ref.level).max())}) bitwise equal on 1 (no mesh), 1, 2 and 4 devices")


def check_training_close(data):
    idx = search_all(build_index(data.s, data.g, k=10, max_level=0), jax.random.PRNGKey(2),
                     data.s, data.g).idx
    cfg = TrainConfig(epochs=2, batch_size=64, width=16, depth=4, target_batch_size=128)
    ref_tr = make_train(cfg, 0.1)
    state0 = ref_tr.init(jax.random.PRNGKey(3))
    ref_state, ref_metrics = jax.jit(ref_tr.run_cycle)(state0, data, idx)
    ref_v = np.asarray(ref_tr.value_fn(ref_state)(data.s, data.g))
    ref_fits = local_fits(ref_tr.value_fn(state0), data, idx, gamma=0.9, batch_size=128)
    moved = max(np.abs(a - b).max() for a, b in zip(leaves(ref_state.params), leaves(state0.params)))
    # ||grad_theta V(s, g)||_1, the largest over the data (for the V tolerance below)
    variables = {"batch_stats": ref_state.batch_stats}
    v_one = lambda p, s, g: ref_tr.network.apply({**variables, "params": p}, s[None], g[None])[0]
    grads = jax.vmap(jax.grad(v_one), in_axes=(None, 0, 0))(ref_state.params, data.s, data.g)
    grad_l1 = float(sum(np.abs(np.asarray(x)).reshape(data.size, -1).sum(1) for x in
                        jax.tree.leaves(grads)).max())
    for n in (2, 4):
        mesh = MESHES[n]
        tr = make_train(cfg, 0.1, mesh=mesh)
        state, metrics = jax.jit(tr.run_cycle)(put(state0, replicated(mesh)),
                                               put(data, replicated(mesh)), idx)
        # Tolerances from what is compared (not from one machine):
        # * parameters: Adam moves each by at most ~lr per step, so gradients that differ by a
        #   relative rho give parameters within lr * steps * rho.  Reduction order changes
        #   gradients by rho ~ 1e-6; a wrong shard or unsynchronised batch norm by rho ~ 1
        #   (the latter measured at 1.3e-2 here).  The bound takes rho = 1e-3.
        steps = cfg.epochs * (data.size // cfg.batch_size)
        bound = cfg.learning_rate * steps * 1e-3
        diff = max(np.abs(a - b).max() for a, b in zip(leaves(ref_state), leaves(state)))
        assert diff < bound, f"{n} devices: state differs by {diff:.2e} > {bound:.1e} after one cycle"
        # * V: to first order |dV| <= ||grad_theta V||_1 * max|d theta| (x2 for second order).
        v = np.asarray(tr.value_fn(state)(data.s, data.g))
        v_diff = np.abs(v - ref_v).max()
        v_bound = 2 * grad_l1 * max(diff, 1e-12) + 1e-6 * np.abs(ref_v).max()
        assert v_diff < v_bound, f"{n} devices: V differs by {v_diff:.2e} > {v_bound:.1e}"
        # * the loss: a float32 mean over ~26 minibatch means of 64 rows: relative rounding
        #   <= ~100 ulp = 1e-5; rtol 1e-4.
        np.testing.assert_allclose(metrics["loss"], ref_metrics["loss"], rtol=1e-4)
        # * local fits: compare the fitted values alpha + beta.a_j at the neighbours' actions,
        #   not beta (nearly collinear actions make beta ill-conditioned: a 1e-7 change of y
        #   moved one beta by 1.5e-6 on another machine).  The fit is a projection H of the
        #   neighbours' values y (||H|| <= 1), so the fitted values differ by at most
        #   ||dy||_2 <= sqrt(k) max|dy|, plus float32 rounding of the fit (1e-5 of max|y|).
        fits = jax.jit(lambda d, i: local_fits(tr.value_fn(state0), d, i, gamma=0.9,
                                               batch_size=128, mesh=mesh))(
            put(data, replicated(mesh)), idx)
        fitted = lambda f: np.asarray(f[0])[:, None] + np.einsum(
            "na,nka->nk", np.asarray(f[1]), np.asarray(data.a)[np.asarray(idx)])
        dy = np.abs(np.asarray(fits[2]) - np.asarray(ref_fits[2])).max()
        y_max = np.abs(np.asarray(ref_fits[2])).max()
        assert dy <= 1e-5 * y_max, f"{n} devices: neighbour values differ by {dy:.2e}"
        fit_diff = np.abs(fitted(fits) - fitted(ref_fits)).max()
        fit_bound = np.sqrt(idx.shape[1]) * dy + 1e-5 * y_max
        assert fit_diff <= fit_bound, f"{n} devices: fitted values differ by {fit_diff:.2e} > {fit_bound:.1e}"
        print(f"train: one cycle ({steps} Adam steps) on {n} devices: parameters, batch "
              f"statistics and Adam moments within {diff:.1e} (bound {bound:.1e}; training "
              f"moved them by up to {moved:.2f}), V within {v_diff:.1e} (bound {v_bound:.1e}); "
              f"fitted local values within {fit_diff:.1e} (bound {fit_bound:.1e})")
    return state


def check_checkpoint_moves_between_device_counts(state):
    with tempfile.TemporaryDirectory() as tmp:
        config = Config(train=TrainConfig(epochs=2, batch_size=64, width=16, depth=4,
                                          target_batch_size=128))
        save_checkpoint(tmp, state, config)  # state replicated over 4 devices
        restored, _ = load_checkpoint(tmp)
        assert len(jax.tree.leaves(restored)[0].devices()) == 1
        for a, b in zip(leaves(state), leaves(restored)):
            np.testing.assert_array_equal(a, b)
        restored, _ = load_checkpoint(tmp, sharding=replicated(MESHES[2]))
        assert len(jax.tree.leaves(restored)[0].devices()) == 2
    print("checkpoint: saved from 4 devices, restored bitwise on 1 and on 2")


def check_default_mesh():
    assert make_mesh().size == 4 == make_mesh(ParallelConfig()).size
    print("mesh: by default all 4 devices")


def check_errors():
    for call, match in ((lambda: make_mesh(5), "only 4 cpu device"),
                        (lambda: make_train(TrainConfig(batch_size=66), 0.1, mesh=MESHES[4]),
                         "batch_size=66 is not divisible by the 4 devices"),
                        (lambda: make_train(TrainConfig(target_batch_size=1001), 0.1,
                                            mesh=MESHES[2]), "target_batch_size=1001")):
        try:
            call()
        except ConfigError as e:
            assert match in str(e), str(e)
        else:
            sys.exit(f"no ConfigError for {match!r}")
    print("errors: too many devices and indivisible batch sizes raise ConfigError")


if __name__ == "__main__":
    data = check_collect_bitwise()
    check_search_bitwise()
    state = check_training_close(data)
    check_checkpoint_moves_between_device_counts(state)
    check_default_mesh()
    check_errors()
    print("all multi-device checks passed")
