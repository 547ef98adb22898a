"""Published success rates on OGBench's pointmaze datasets (%, mean and standard deviation over
8 seeds where the source gives it), for the benchmark table beside what runs here measure.

OGBench's table (Park et al. 2024, "OGBench: Benchmarking Offline Goal-Conditioned RL", Table 2:
GCBC, GCIVL, GCIQL, QRL, CRL, HIQL at 1M steps of batch 1024) and later work: SAW (Zhou & Kao,
NeurIPS 2025) and S2AW (Zhou, Dong & Kao).  Standard deviations only where the sources read
here (shared/DESIGN.md §8-§9, issue 59) state them; teleport's numbers were not found.
"""

from __future__ import annotations

OGBENCH = ("OGBench's agents from OGBench (Park et al. 2024), 8 seeds; SAW (Zhou & Kao 2025) and S2AW "
           "(Zhou, Dong & Kao) from their papers")
LATER = ("saw", "s2aw")  # not OGBench's agents: published numbers only

# dataset -> method -> (mean %, std % or None)
PUBLISHED: dict[str, dict[str, tuple[float, float | None]]] = {
    "pointmaze-medium-navigate": {"gcbc": (9, 6), "gcivl": (63, 6), "gciql": (53, 8), "qrl": (82, 5),
                                  "crl": (29, 7), "hiql": (79, 5), "saw": (97, 2), "s2aw": (96, 3)},
    "pointmaze-large-navigate": {"gcbc": (29, None), "gcivl": (45, None), "gciql": (34, None),
                                 "qrl": (86, 9), "crl": (39, None), "hiql": (58, None), "saw": (85, 10),
                                 "s2aw": (83, None)},
    "pointmaze-giant-navigate": {"gcbc": (1, None), "gcivl": (0, None), "gciql": (0, None),
                                 "qrl": (68, 7), "crl": (27, None), "hiql": (46, None), "saw": (68, None),
                                 "s2aw": (73, 9)},
    "pointmaze-medium-stitch": {"gcbc": (23, None), "gcivl": (70, None), "gciql": (21, None),
                                "qrl": (80, 12), "crl": (0, None), "hiql": (74, None), "saw": (87, 4)},
    "pointmaze-large-stitch": {"gcbc": (7, None), "gcivl": (12, None), "gciql": (31, None),
                               "qrl": (84, 15), "crl": (0, None), "hiql": (13, None), "saw": (8, 9)},
    "pointmaze-giant-stitch": {"gcbc": (0, None), "gcivl": (0, None), "gciql": (0, None),
                               "qrl": (50, 8), "crl": (0, None), "hiql": (0, None), "saw": (0, None)},
    "pointmaze-teleport-navigate": {},
    "pointmaze-teleport-stitch": {},
}

#: OGBench's training budget of every published number: gradient steps x batch size
OGBENCH_BUDGET = (1_000_000, 1024)
