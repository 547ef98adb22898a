"""The paper's ablations as studies (§IV-C Eq. 7 vs 8, §IV-E DQN vs Double DQN, the
neighbourhood size k, resampled neighbourhoods, the number of cycles).

Every variant is the ``paper`` preset with one change, run as a study over the same
seeds (default 0..4).  The unchanged ``default`` is read from the main study
(``make study``: runs/study_paper), restricted to these seeds, and its datasets are
copied into each variant (same collection config: nothing is collected twice).  The
20-cycle variant starts from the main study's 10-cycle checkpoints (the first 10
cycles are the same computation) and trains 10 more.

    .venv/bin/python experiments/ablations.py [--seeds 5] [--main runs/study_paper]
        [--out runs/ablations] [--only unclipped double_dqn ...]

Writes ``<out>/<variant>/`` (complete studies), ``<out>/ablations.md`` (the table),
``<out>/ablations.json`` and ``<out>/targets_over_cycles.png`` (target mean, loss and clip
fraction per cycle, mean and 95 % CI over the seeds).
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import jax
import numpy as np

from lazyq_jax.checkpoint import load_checkpoint, save_checkpoint
from lazyq_jax.config import override, preset
from lazyq_jax.stats import format_ci, t_interval
from lazyq_jax.study import method_summary, run_study

VARIANTS = {
    "unclipped": (["train.clip=false"], "Eq. (7) targets, no max-bound"),
    "double_dqn": (["train.double_dqn=true"], "Double-DQN targets, Eq. (13)-(14)"),
    "k10": (["neighbours.k=10"], "k = 10 neighbours"),
    "k40": (["neighbours.k=40"], "k = 40 neighbours"),
    "resampled": (["train.resample_neighbours=true"], "new neighbour samples every cycle"),
    "cycles20": (["train.cycles=20"], "20 cycles x 10 epochs"),
}
CURVES = ("target_mean", "loss", "clip_fraction")


def copy_datasets(main: Path, out: Path, seeds) -> None:
    for seed in seeds:
        src, dst = main / "seeds" / str(seed), out / "seeds" / str(seed)
        if not (dst / "dataset.npz").exists():
            dst.mkdir(parents=True, exist_ok=True)
            for name in ("dataset.npz", "dataset_summary.json"):
                shutil.copy(src / name, dst / name)


def seed_slice_checkpoints(main: Path, out: Path, main_seeds, seeds, base) -> None:
    """The main study's checkpoints restricted to ``seeds`` (a study can extend them)."""
    ckpt = out / "lazy" / "checkpoints"
    if ckpt.exists():
        return
    rows = [main_seeds.index(s) for s in seeds]
    state, _ = load_checkpoint(main / "lazy" / "checkpoints", seeds=main_seeds)
    save_checkpoint(ckpt, jax.tree.map(lambda x: x[np.asarray(rows)], state), base, seeds=seeds)
    lines = []
    for line in (main / "lazy" / "metrics.jsonl").read_text().splitlines():
        record = json.loads(line)
        lines.append(json.dumps({k: ([v[i] for i in rows] if isinstance(v, list) else v)
                                 for k, v in record.items()}))
    (out / "lazy" / "metrics.jsonl").write_text("\n".join(lines) + "\n")


def curves(study: Path, rows=None) -> dict:
    """Per-cycle mean and CI over the seeds (``rows``: indices of some of the study's seeds)
    of the metrics in :data:`CURVES`."""
    records = [json.loads(line) for line in (study / "lazy" / "metrics.jsonl").read_text().splitlines()]
    out = {}
    for name in CURVES:
        per_cycle = [t_interval(r[name] if rows is None else [r[name][i] for i in rows],
                                bounds=None) for r in records]
        out[name] = {"mean": [c["mean"] for c in per_cycle], "ci95": [c["ci95"] for c in per_cycle]}
    return out


def plot(all_curves: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(CURVES), figsize=(15, 4), constrained_layout=True)
    for ax, name in zip(axes, CURVES):
        for variant, c in all_curves.items():
            m = np.array(c[name]["mean"])
            x = np.arange(1, m.size + 1)
            line, = ax.plot(x, m, marker=".", label=variant)
            if c[name]["ci95"][0] is not None:
                ci = np.array(c[name]["ci95"])
                ax.fill_between(x, ci[:, 0], ci[:, 1], color=line.get_color(), alpha=0.15)
        ax.set_xlabel("cycle")
        ax.set_title({"target_mean": "mean target Y", "loss": "final-epoch loss",
                      "clip_fraction": "fraction of targets clipped (Eq. 8)"}[name])
        if name == "loss":
            ax.set_yscale("log")
        if name == "target_mean":  # the unclipped targets grow by orders of magnitude
            ax.set_yscale("symlog", linthresh=1.0)
    axes[0].legend(fontsize=8)
    fig.suptitle("Ablations over cycles: mean and 95 % CI over seeds")
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--main", type=Path, default=Path("runs/study_paper"))
    ap.add_argument("--out", type=Path, default=Path("runs/ablations"))
    ap.add_argument("--only", nargs="*", default=list(VARIANTS))
    ap.add_argument("--preset", default="paper", help="the base preset (smoke: a quick try)")
    args = ap.parse_args()
    seeds = list(range(args.seeds))
    base = preset(args.preset)
    main_results = json.loads((args.main / "results.json").read_text())
    main_seeds = main_results["seeds"]
    missing = sorted(set(seeds) - set(main_seeds))
    if missing:
        raise SystemExit(f"{args.main} lacks seeds {missing}; run `make study` first")
    main_eval = [r for r in json.loads((args.main / "lazy" / "eval.json").read_text())
                 if r["seed"] in seeds]
    rows = {"default": (method_summary(main_eval), "paper preset (Eq. 8, DQN targets, k = 20)")}
    all_curves = {"default": curves(args.main, [main_seeds.index(s) for s in seeds])}
    for name in args.only:
        changes, what = VARIANTS[name]
        config = override(base, changes)
        out = args.out / name
        copy_datasets(args.main, out, seeds)
        if name == "cycles20":
            seed_slice_checkpoints(args.main, out, main_seeds, seeds, config)
        results = run_study(config, out, seeds=seeds, resume=True, progress=False)
        rows[name] = (results["methods"]["lazy"], what)
        all_curves[name] = curves(out)
    keys = ("axis_correct_rate", "diagonal_correct_rate", "overall_correct_rate",
            "long_horizon_success_rate")
    lines = [f"Seeds {seeds}; mean [95 % Student-t CI over seeds].", "",
             "| variant | what | axis correct | diagonal correct | all 16 correct | long horizon | "
             "final mean target | final clip fraction |", "|---|---|---|---|---|---|---|---|"]
    for name, (m, what) in rows.items():
        c = all_curves[name]
        lines.append(f"| {name} | {what} | " + " | ".join(format_ci(m["summary"][k]) if k in m["summary"] else "–"
                                                          for k in keys)
                     + f" | {c['target_mean']['mean'][-1]:+.3f} | {c['clip_fraction']['mean'][-1]:.1%} |")
    table = "\n".join(lines) + "\n"
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "ablations.md").write_text(table)
    assert args.preset == "paper" or "smoke" in str(args.out), "write smoke tries elsewhere"
    (args.out / "ablations.json").write_text(json.dumps(
        {"seeds": seeds, "variants": {n: {"what": w, "summary": m["summary"],
                                          "per_seed": m["per_seed"], "curves": all_curves[n]}
                                      for n, (m, w) in rows.items()}}, indent=1))
    plot(all_curves, args.out / "targets_over_cycles.png")
    print(table)


if __name__ == "__main__":
    main()
