"""Run by tests/test_parallel.py as one of two processes (2 CPU devices each, launched by
hand with ``jax.distributed`` as on a cluster): the general neighbour search over the global
4-device mesh.  Each process searches on its own 2 devices and writes what it got to
``OUT.<process>.npz``; the test compares both with one process and no mesh.

    python tests/two_process_search.py OUT   (with JAX_NUM_PROCESSES, JAX_PROCESS_ID,
                                             JAX_COORDINATOR_ADDRESS, XLA_FLAGS set)
"""

import sys

import jax
import numpy as np

from lazyq_jax.config import ParallelConfig
from lazyq_jax.neighbours import find_neighbours
from lazyq_jax.neighbours.nd import _local_mesh
from lazyq_jax.parallel import make_mesh, maybe_initialize_distributed


def search_inputs():
    """3-D states (a tenth of them sparse, so that queries grow past level 3), vector goals."""
    rng = np.random.default_rng(5)
    s = rng.uniform(-1, 1, (2000, 3)).astype(np.float32)
    s[:200] *= 5
    g = rng.uniform(-1, 1, (2000, 2)).astype(np.float32)
    return jax.random.PRNGKey(6), s, g, {"k": 10, "radius_s": 0.1, "radius_g": 0.3}


def main(out: str) -> None:
    assert maybe_initialize_distributed(ParallelConfig(distributed=True))
    mesh = make_mesh(0)
    assert jax.process_count() == 2 and mesh.size == 4, (jax.process_count(), mesh)
    assert _local_mesh(mesh).size == 2  # the chunks run on this process's 2 devices
    key, s, g, kw = search_inputs()
    nb = find_neighbours(key, s, g, s, g, mesh=mesh, **kw)
    np.savez(f"{out}.{jax.process_index()}.npz", idx=np.asarray(nb.idx), level=np.asarray(nb.level))


if __name__ == "__main__":
    main(sys.argv[1])
