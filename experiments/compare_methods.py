"""Lazy Q against the alternatives on the same data, seeds, protocols and budget.

A study of the reporting seeds (default 0..4) with every method: lazy Q (the paper
preset), the baselines with the options chosen by experiments/baseline_sweep.py
(``runs/baseline_sweep/best.json``) at ``--budget`` times lazy Q's gradient steps,
and the random and scripted controllers.  Lazy Q's datasets and trained states are
taken from the main study (``make study``: runs/study_paper, restricted to these
seeds) instead of being trained again; the other methods train on those datasets.

    .venv/bin/python experiments/compare_methods.py [--seeds 5] [--first-seed 0] [--budget 1]
        [--main runs/study_paper] [--best runs/baseline_sweep/best.json]
        [--out runs/study_methods] [--methods iql td3bc dqn naf bc random scripted]

The study writes ``<out>/results.json``, ``summary.md`` and ``figures/methods.png``.
With ``--budget 4`` (and e.g. ``--seeds 2 --out runs/study_methods_4x --no-lazy``) it
shows whether a method is budget-limited.  ``--main none`` runs everything afresh in
``<out>`` (collects the datasets and trains lazy Q there too: e.g. on another machine).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from lazyq_jax.config import override, preset
from lazyq_jax.study import run_study, summary_markdown

from ablations import copy_datasets, seed_slice_checkpoints


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--first-seed", type=int, default=0,
                    help="the seeds are first-seed .. first-seed + seeds - 1")
    ap.add_argument("--budget", type=float, default=1.0)
    ap.add_argument("--main", type=Path, default=Path("runs/study_paper"),
                    help="the study whose datasets and lazy Q are reused; 'none': afresh")
    ap.add_argument("--best", type=Path, default=Path("runs/baseline_sweep/best.json"))
    ap.add_argument("--out", type=Path, default=Path("runs/study_methods"))
    ap.add_argument("--methods", nargs="*",
                    default=["iql", "td3bc", "dqn", "naf", "bc", "random", "scripted"])
    ap.add_argument("--no-lazy", action="store_true", help="only the other methods")
    ap.add_argument("--set", action="append", default=[], help="lazy Q config override")
    ap.add_argument("--progress", action="store_true", help="progress bars on stderr")
    args = ap.parse_args()
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    config = override(preset("paper"), args.set)
    best = json.loads(args.best.read_text()) if args.best.exists() else {}
    specs = [] if args.no_lazy else ["lazy"]
    for m in args.methods:
        if m in ("random", "scripted"):
            specs.append(m)
        else:
            options = best.get(m, "")
            specs.append(":".join([m, *([options] if options else []),
                                   *([f"budget={args.budget:g}"] if args.budget != 1 else [])]))
    if str(args.main) != "none":
        main_seeds = json.loads((args.main / "results.json").read_text())["seeds"]
        copy_datasets(args.main, args.out, seeds)
        if not args.no_lazy and not args.set:  # the main study's lazy Q, these seeds
            seed_slice_checkpoints(args.main, args.out, main_seeds, seeds, config)
    results = run_study(config, args.out, seeds=seeds, methods=specs, resume=True,
                        progress=args.progress)
    print(summary_markdown(results))


if __name__ == "__main__":
    main()
