"""Neighbourhoods ``B(s0, g0)`` of paper §V-A-2, for any state and goal space.

One semantics (the float32 membership test of :mod:`lazyq_jax.neighbours.common`: a ball
of ``radius_s * growth**L`` in state space and ``radius_g * growth**L`` in goal space, ``L``
the smallest level holding ``k`` points, ``k`` members drawn uniformly without
replacement), three engines:

* :mod:`~lazyq_jax.neighbours.grid`: 2-D states with angle goals (the paper's case), a
  grid hash with fixed bounds and capacities so that seeds share compiled passes,
  the device mesh, and a jittable bounded query (``query_neighbours``);
* :mod:`~lazyq_jax.neighbours.nd`: any ``d_s <= 10`` with angle, vector or no goals, the
  device mesh (chunks dealt to the devices);
* :mod:`~lazyq_jax.neighbours.query`: the policy's jittable per-step query in any space
  (the lazy policy's, on every task), and :mod:`~lazyq_jax.neighbours.scan`, a scan of all
  data a query (its reference and fallback).

nd and query share one layout (:mod:`~lazyq_jax.neighbours.layout`: the data sorted by the
cells of a few axes, a query's stencil as ranges) and one cost model that picks it
(:mod:`~lazyq_jax.neighbours.cost`); every engine shares the core after the layout
(:mod:`~lazyq_jax.neighbours.common`: items, membership words, level, sample).
:func:`find_neighbours` picks the engine from the shapes.
"""

from __future__ import annotations

import numpy as np
from jax.sharding import Mesh

from lazyq_jax.neighbours.common import Neighbours, _check_params, radius_tables, wrap_angle
from lazyq_jax.neighbours.grid import GridIndex, build_index, check_found, query_neighbours, search_all
from lazyq_jax.neighbours.layout import _check_match, _points, _space
from lazyq_jax.neighbours.nd import find_neighbours_nd
from lazyq_jax.neighbours.scan import ScanIndex, build_scan_index, query_neighbours_scan

__all__ = ["GridIndex", "Neighbours", "ScanIndex", "build_index", "build_scan_index", "check_found",
           "find_neighbours", "is_grid_space", "query_neighbours", "query_neighbours_scan",
           "radius_tables", "search_all", "wrap_angle"]


def is_grid_space(data_s, data_g) -> bool:
    """Whether the 2-D grid serves this space: states ``[N, 2]`` with angle goals ``[N]``."""
    return (np.ndim(data_s) == 2 and np.shape(data_s)[1] == 2 and data_g is not None
            and np.ndim(data_g) == 1)


def find_neighbours(key, data_s, data_g, query_s, query_g, *, k=20, radius_s=0.06, radius_g=0.1,
                    growth=2 ** (1 / 3), mesh: Mesh | None = None) -> Neighbours:
    """Neighbourhoods of paper §V-A-2 (the exact semantics: :mod:`lazyq_jax.neighbours.common`).

    The shapes decide the space: states ``[N, d_s]``; goals ``[N]`` (an angle),
    ``[N, d_g]`` (a vector, Euclidean) or ``None``.  Two-dimensional states with angle
    goals (the push task) use the grid (:func:`build_index`, :func:`search_all`);
    every other space goes to :func:`lazyq_jax.neighbours.nd.find_neighbours_nd` (same
    semantics).  ``mesh``: the search runs on its devices (the same result as on one device,
    checked bitwise on CPU devices).  Raises ``ValueError`` before any compilation for bad
    shapes, NaN/inf coordinates, ``k <= 0`` or ``k > N``, non-positive radii or
    ``growth <= 1``.
    """
    _check_params(k, radius_s, radius_g, growth)
    _, *space = _space(data_s, data_g, "data")
    _check_match(space, _space(query_s, query_g, "query")[1:])
    if not is_grid_space(data_s, data_g):
        return find_neighbours_nd(key, data_s, data_g, query_s, query_g, k=k, radius_s=radius_s,
                                  radius_g=radius_g, growth=growth, mesh=mesh)
    _points(query_s, query_g, "query")  # NaN/inf before the build compiles
    index = build_index(data_s, data_g, k=k, radius_s=radius_s, radius_g=radius_g, growth=growth,
                        max_level=0)  # validates the data on the host before its first program
    return search_all(index, key, query_s, query_g, mesh=mesh)
