"""Accuracy vs time of the value network's width at paper scale (chooses the default).

For each width: train the paper preset (10 x 10) on the same dataset, evaluate both
protocols with the same evaluation seed, and print training time, final loss and
the evaluation results.  The dataset is collected once (into the first run dir)
and reused by the others.

    .venv/bin/python experiments/width_study.py --widths 32 64 128 [--runs-dir runs/width]
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

from lazyq_jax.config import override, preset
from lazyq_jax.evaluate import evaluate_run
from lazyq_jax.pipeline import fit


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--widths", type=int, nargs="+", default=[32, 64, 128])
    ap.add_argument("--runs-dir", type=Path, default=Path("runs/width"))
    ap.add_argument("--set", action="append", default=[], help="extra config overrides")
    args = ap.parse_args()
    rows, dataset = [], None
    for width in args.widths:
        config = override(preset("paper"), [f"train.width={width}", *args.set])
        run_dir = args.runs_dir / f"w{width}"
        run_dir.mkdir(parents=True, exist_ok=True)
        if dataset is not None and not (run_dir / "dataset.npz").exists():
            shutil.copy(dataset, run_dir / "dataset.npz")
        fit(config, run_dir, overwrite=True, progress=False)  # a study starts afresh
        dataset = run_dir / "dataset.npz"
        results = evaluate_run(run_dir, figures=False)
        timings = json.loads((run_dir / "timings.json").read_text())
        last = json.loads((run_dir / "metrics.jsonl").read_text().splitlines()[-1])
        rows.append((width, timings["train_s"], last["loss"], results))
    print(f"\n{'width':>5} | {'train s':>7} {'final loss':>10} | {'axis correct':>12} "
          f"{'all correct':>11} | {'long horizon':>12}")
    for width, seconds, loss, r in rows:
        a, b = r["protocol_a"], r["protocol_b"]
        print(f"{width:>5} | {seconds:>7.0f} {loss:>10.5f} | {a['axis_correct_rate']:>12.1%} "
              f"{a['overall_correct_rate']:>11.1%} | {b['successes']:>8}/{b['rollouts']}")


if __name__ == "__main__":
    main()
