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
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from lazyq_jax.checkpoint import load_checkpoint, save_checkpoint  # noqa: E402
from lazyq_jax.config import ConfigError, ParallelConfig, TrainConfig  # noqa: E402
from lazyq_jax.neighbours import build_index, find_neighbours, search_all  # noqa: E402
from lazyq_jax.neighbours.nd import build_index_nd, search_all_nd  # noqa: E402
from lazyq_jax.parallel import make_mesh, put, replicated  # noqa: E402
from lazyq_jax.targets import lazy_target, local_fits  # noqa: E402
from lazyq_jax.tasks.push import CollectConfig  # noqa: E402
from lazyq_jax.tasks.push.collect import collect  # noqa: E402
from lazyq_jax.train import make_train  # noqa: E402

assert jax.device_count() == 4, jax.devices()
MESHES = {n: make_mesh(n) for n in (1, 2, 4)}


def leaves(tree):
    return [np.asarray(x) for x in jax.tree.leaves(tree)]


def check_collect_bitwise():
    # 6 chunks of 15 episodes: 4 devices get an uneven last call (padding).
    cfg = CollectConfig(n_starts=90, n_goals=5, chunk_size=16, start_range=0.6)
    ref = collect(jax.random.PRNGKey(7), cfg, progress=False)
    out = collect(jax.random.PRNGKey(7), cfg, mesh=MESHES[4], progress=False)
    for a, b in zip(leaves(ref), leaves(out)):
        np.testing.assert_array_equal(a, b, err_msg="collect on 4 devices")
    assert int(np.asarray(ref.done).sum()) > 0, "no push moved the disk: the check is too weak"
    print(f"collect: {ref.size} rows bitwise equal on 1 (no mesh) and 4 devices")
    return ref


def check_search_bitwise():
    rng = np.random.default_rng(0)
    s = rng.uniform(-1, 1, (3001, 2)).astype(np.float32)
    s[:300] *= 4  # sparse points that need several growth passes
    g = rng.uniform(-np.pi, np.pi, 3001).astype(np.float32)
    index = build_index(s, g, k=12, max_level=0)
    ref = search_all(index, jax.random.PRNGKey(1), s, g)
    assert int(np.asarray(ref.level).max()) >= 3, "no query grew: the check is too weak"
    out = search_all(index, jax.random.PRNGKey(1), s, g, mesh=MESHES[4])
    for a, b in zip(leaves(ref), leaves(out)):
        np.testing.assert_array_equal(a, b, err_msg="search on 4 devices")
    print("search: 3001 queries (levels up to "
          f"{int(np.asarray(ref.level).max())}) bitwise equal on 1 (no mesh) and 4 devices")


def check_search_general_spaces_bitwise():
    """The general engine (any d_s; angle and vector goals; the mesh path does not depend on
    the kind of goal, and tests/test_neighbours_nd.py checks goals that are absent): its chunks
    run 4 at a time on 4 devices give bitwise the one-device neighbourhoods, levels > 3
    included."""
    rng = np.random.default_rng(3)
    s = rng.uniform(-1, 1, (2500, 3)).astype(np.float32)
    s[:250] *= 5  # sparse points that need several growth passes
    goals = {"angle": rng.uniform(-np.pi, np.pi, 2500).astype(np.float32),
             "vector": rng.uniform(-1, 1, (2500, 2)).astype(np.float32)}
    key = jax.random.PRNGKey(4)
    for kind, g in goals.items():
        index = build_index_nd(s, g, k=10, radius_s=0.1, radius_g=0.3)
        stats = {}
        # small chunks: the first pass has several per device
        ref = search_all_nd(index, key, s, g, chunk_items=512, stats=stats)
        assert int(np.asarray(ref.level).max()) > 3, f"{kind}: no query grew past level 3"
        assert stats["passes"][0]["chunks"] >= 8, stats["passes"][0]
        out = search_all_nd(index, key, s, g, chunk_items=512, mesh=MESHES[4])
        for a, b in zip(leaves(ref), leaves(out)):
            np.testing.assert_array_equal(a, b, err_msg=f"general search ({kind}) on 4 devices")
    # chunks that overflow a forced capacity on the mesh: re-run in new groups, still bitwise
    stats = {}
    out = search_all_nd(index, key, s, g, chunk_items=512, item_capacity=8, mesh=MESHES[4],
                        stats=stats)
    assert stats["overflow_chunks"] > 0, stats
    for a, b in zip(leaves(ref), leaves(out)):
        np.testing.assert_array_equal(a, b, err_msg="overflowing chunks on 4 devices")
    # find_neighbours takes the mesh for general spaces too: its own index (the same grid: the
    # queries are the data) and chunking, on 2 devices; a query's bits depend on its row only,
    # so the result is the small chunks' one-device result above
    via = find_neighbours(key, s, g, s, g, k=10, radius_s=0.1, radius_g=0.3, mesh=MESHES[2])
    for a, b in zip(leaves(ref), leaves(via)):
        np.testing.assert_array_equal(a, b, err_msg="find_neighbours (vector goals) on 2 devices")
    print("general search: 3-D states with angle and vector goals (2500 queries, levels > 3, "
          ">= 8 chunks a pass; overflowing chunks re-run) bitwise equal on 1 (no mesh) and 4 "
          "devices; find_neighbours on 2")


def check_first_update(data):
    """One training cycle of ONE Adam step (the whole dataset is one minibatch) on 4 devices
    against one device: what is deterministic up to reduction order.  Training
    outcomes after many steps are not compared (training is chaotic)."""
    idx = search_all(build_index(data.s, data.g, k=10, max_level=0), jax.random.PRNGKey(2),
                     data.s, data.g).idx
    n = data.size // 4 * 4
    data = jax.tree.map(lambda x: x[:n], data)
    idx = jnp.minimum(idx[:n], n - 1)
    cfg = TrainConfig(epochs=1, batch_size=n, width=16, depth=4, target_batch_size=128)
    ref_tr = make_train(cfg, 0.1)
    state0 = ref_tr.init(jax.random.PRNGKey(3), data)
    ref_state, ref_metrics = jax.jit(ref_tr.run_cycle)(state0, data, idx)
    # The first step's gradient on the reference, from the targets of the frozen network.
    alpha, beta, y_nb = local_fits(ref_tr.value_fn(state0), data, idx, gamma=cfg.gamma, batch_size=128)
    y = lazy_target(alpha, beta, y_nb, 0.1)[0]

    def loss(params):
        v, _ = ref_tr.network.apply({"params": params, "batch_stats": state0.batch_stats}, data.s,
                                    data.g, train=True, mutable=["batch_stats"])
        return jnp.mean((v - y) ** 2)

    grads = leaves(jax.grad(loss)(state0.params))
    n_dev = 4  # each device holds a quarter of the batch
    mesh = MESHES[n_dev]
    tr = make_train(cfg, 0.1, mesh=mesh)
    state, metrics = jax.jit(tr.run_cycle)(put(state0, replicated(mesh)),
                                           put(data, replicated(mesh)), idx)
    # Tolerances from what is compared:
    # * the loss, the targets' statistics: float32 means over n rows summed in another
    #   order: relative rounding <= n * 2^-24 (worst case).
    rtol = n * 2.0 ** -24
    for name in ("loss_first_epoch", "target_mean", "target_std", "beta_norm_mean"):
        np.testing.assert_allclose(metrics[name], ref_metrics[name], rtol=rtol, err_msg=name)
    np.testing.assert_allclose(metrics["clip_fraction"], ref_metrics["clip_fraction"], atol=2 / n)
    # * the parameters after Adam's first step p - lr g / (|g| + eps): where |g| >> eps
    #   the step is lr sign(g) up to lr eps |dg| / g^2, i.e. equal to 1e-3 lr for any
    #   gradient change |dg| < 1e-3 g^2 / eps (reduction order: ~1e-7 |g|); where |g| is
    #   tiny the step can be anything in [-lr, lr].  A wrong shard or unsynchronised
    #   batch norm changes the gradient by O(|g|) and flips signs.
    lr = cfg.learning_rate
    for p, p_ref, g in zip(leaves(state.params), leaves(ref_state.params), grads):
        big = np.abs(g) > 1e-4
        assert big.mean() > 0.5, "too few informative gradients: the check is too weak"
        diff = np.abs(p - p_ref)
        assert diff[big].max(initial=0) < 1e-3 * lr, f"{n_dev} devices: step differs by {diff[big].max():.2e}"
        assert diff.max() <= 2 * lr * (1 + 1e-6)
    # * the batch-norm statistics: the whole minibatch's (synchronised) mean and variance,
    #   float32 sums of n rows: within n * 2^-24 of their magnitude.
    for a, b in zip(leaves(state.batch_stats), leaves(ref_state.batch_stats)):
        np.testing.assert_allclose(a, b, rtol=0, atol=rtol * (np.abs(b).max() + 1e-12) + 1e-7)
    print(f"train: the first Adam step on {n_dev} devices equals one device's (loss, targets "
          f"within rtol {rtol:.0e}; steps of informative gradients within 1e-3 lr; batch "
          "statistics within rounding)")
    return state


def check_checkpoint_moves_between_device_counts(state):
    with tempfile.TemporaryDirectory() as tmp:
        abstract = jax.eval_shape(lambda: state)
        save_checkpoint(tmp, state, 1)  # state replicated over 4 devices
        restored, _ = load_checkpoint(tmp, abstract)
        assert len(jax.tree.leaves(restored)[0].devices()) == 1
        for a, b in zip(leaves(state), leaves(restored)):
            np.testing.assert_array_equal(a, b)
        restored, _ = load_checkpoint(tmp, abstract, sharding=replicated(MESHES[2]))
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
    check_search_general_spaces_bitwise()
    state = check_first_update(data)
    check_checkpoint_moves_between_device_counts(state)
    check_default_mesh()
    check_errors()
    print("all multi-device checks passed")
