"""How the friction law shapes the data and the agent (the paper's world vs easier ones).

For each world (a friction setting of the push scene):

1. data, at paper scale for ``--data-seeds`` seeds: positive rewards per goal octant
   (mean over seeds) and the ratio of the largest diagonal octant to the smallest axis
   octant; and where head-on pushes at 30 / 40 / 44 degrees move the disk;
2. the agent, for the worlds in ``--train``: a study of ``--train-seeds`` seeds (the
   whole pipeline), protocol-A correct rate per goal direction.  A world whose study
   already exists under ``--reuse`` (e.g. the main study of the paper world) is read
   from there instead of being trained again.

    .venv/bin/python experiments/anisotropy_sweep.py [--data-seeds 4] [--train-seeds 2]
        [--out runs/sweep] [--reuse paper=runs/study_paper forgiving=runs/study_forgiving]

Writes ``<out>/sweep.json``, ``<out>/sweep.md`` and ``<out>/sweep.png``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from lazyq_jax.config import FORGIVING_PUSH, PushConfig, preset
from lazyq_jax.data import collect, dataset_summary
from lazyq_jax.env import PushEnv
from lazyq_jax.pipeline import run_keys
from lazyq_jax.stats import t_interval
from lazyq_jax.study import run_study, seed_config

# name -> (PushConfig, shown in the figure as)
WORLDS = {
    "isotropic": (PushConfig(friction_coefficient=0.0), "Coulomb mu=0 (viscous only)"),
    "coulomb_0.5": (PushConfig(friction_coefficient=0.5), "Coulomb mu=0.5"),
    "coulomb_1": (PushConfig(friction_coefficient=1.0), "Coulomb mu=1"),
    "paper": (PushConfig(), "Coulomb mu=2 (paper preset)"),
    "coulomb_4": (PushConfig(friction_coefficient=4.0), "Coulomb mu=4"),
    "fluid_100": (dataclasses.replace(FORGIVING_PUSH, anisotropy=100.0), "quadratic drag 100"),
    "forgiving": (FORGIVING_PUSH, "quadratic drag 200 (forgiving preset)"),
    "fluid_300": (dataclasses.replace(FORGIVING_PUSH, anisotropy=300.0), "quadratic drag 300 (its limit)"),
}


def head_on(push: PushConfig, degrees=(30.0, 40.0, 44.0)) -> list[float]:
    """Directions (degrees) in which head-on pushes at ``degrees`` move the disk (float64)."""
    a = np.radians(np.asarray(degrees))
    d = np.stack([np.cos(a), np.sin(a)], 1)
    with jax.enable_x64(True):
        env = PushEnv(push)
        _, delta = jax.jit(jax.vmap(env.step))(env.reset(jnp.asarray(-0.33 * d, jnp.float32)),
                                                jnp.asarray(d, jnp.float32))
    delta = np.asarray(delta)
    return np.degrees(np.arctan2(delta[:, 1], delta[:, 0])).round(1).tolist()


def world_config(preset_name: str, push: PushConfig):
    base = preset(preset_name)
    return dataclasses.replace(base, collect=dataclasses.replace(base.collect, push=push))


def data_stats(config, seeds) -> dict:
    push = config.collect.push
    counts = []
    for seed in seeds:
        data = collect(run_keys(seed_config(config, seed))["collect"], config.collect, progress=False)
        s = dataset_summary(data, config.collect.n_goals)
        counts.append([o["positive"] for o in s["reward_by_goal_octant"]])
    counts = np.array(counts)
    mean = counts.mean(axis=0)
    return {"positives_per_seed": counts.tolist(), "positives_mean": mean.round(1).tolist(),
            "diagonal_to_axis_of_means": float(mean[1::2].max() / mean[0::2].min()),
            "head_on_30_40_44": head_on(push)}


def agent_stats(name: str, config, seeds, out: Path, reuse: dict) -> dict:
    if name in reuse:
        results = json.loads((Path(reuse[name]) / "results.json").read_text())
        rows = [r for r in results["methods"]["lazy"]["per_seed"] if r["seed"] in seeds]
        source = str(reuse[name])
    else:
        results = run_study(config, out / name, seeds=seeds, resume=True, progress=False)
        rows = results["methods"]["lazy"]["per_seed"]
        source = str(out / name)
    per_direction = np.array([r["per_direction_correct_rate"] for r in rows])
    return {"source": source, "seeds": [r["seed"] for r in rows],
            "per_direction_mean": per_direction.mean(axis=0).round(4).tolist(),
            **{key: t_interval([r[f"{key}_correct_rate"] for r in rows])
               for key in ("axis", "diagonal") if np.isfinite(rows[0][f"{key}_correct_rate"])}}


def plot(report: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(report)
    fig, (left, right) = plt.subplots(1, 2, figsize=(14, 4.8), constrained_layout=True)
    x = np.arange(len(names))
    axis = [np.mean(report[n]["data"]["positives_mean"][0::2]) for n in names]
    diag = [np.mean(report[n]["data"]["positives_mean"][1::2]) for n in names]
    left.bar(x - 0.2, axis, 0.4, label="axis octants (0°, 90°, 180°, 270°)")
    left.bar(x + 0.2, diag, 0.4, label="diagonal octants")
    for i, n in enumerate(names):
        left.text(i, max(axis[i], diag[i]) + 5, f"{report[n]['data']['diagonal_to_axis_of_means']:.2f}",
                  ha="center", fontsize=8)
    left.set_xticks(x, [WORLDS[n][1] for n in names], rotation=30, ha="right", fontsize=8)
    left.set_ylabel("+1 rewards per goal octant (mean over seeds)")
    left.set_title("Data: positives per octant (numbers: largest diagonal / smallest axis)")
    left.legend(fontsize=8)
    trained = [n for n in names if "agent" in report[n]]
    for n in trained:
        rates = report[n]["agent"]["per_direction_mean"]
        right.plot(np.arange(len(rates)) * 360 / len(rates), rates, marker="o", label=WORLDS[n][1])
    right.set_xticks(np.arange(0, 360, 45))
    right.set_xlabel("goal direction (degrees)")
    right.set_ylabel("protocol A correct (mean over seeds)")
    right.set_ylim(-0.02, 1.02)
    right.set_title("Agent: correct pushes per goal direction")
    right.legend(fontsize=8)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--worlds", nargs="*", default=list(WORLDS))
    ap.add_argument("--train", nargs="*", default=["isotropic", "coulomb_0.5", "coulomb_1", "paper",
                                                   "forgiving"])
    ap.add_argument("--data-seeds", type=int, default=4)
    ap.add_argument("--train-seeds", type=int, default=2)
    ap.add_argument("--out", type=Path, default=Path("runs/sweep"))
    ap.add_argument("--reuse", nargs="*", default=[], help="world=study_dir (read, not trained)")
    ap.add_argument("--preset", default="paper", help="scale of data and studies (smoke: a quick try)")
    args = ap.parse_args()
    reuse = dict(item.split("=", 1) for item in args.reuse)
    args.out.mkdir(parents=True, exist_ok=True)
    report = {}
    for name in args.worlds:
        config = world_config(args.preset, WORLDS[name][0])
        report[name] = {"label": WORLDS[name][1], "push": dataclasses.asdict(config.collect.push),
                        "data": data_stats(config, range(args.data_seeds))}
        if name in args.train:
            report[name]["agent"] = agent_stats(name, config, list(range(args.train_seeds)),
                                                args.out, reuse)
        print(name, json.dumps({k: v for k, v in report[name].items() if k != "push"}), flush=True)
    (args.out / "sweep.json").write_text(json.dumps(report, indent=1))
    lines = ["| world | +1 per octant, mean (0°, 45°, ..., 315°) | largest diag / smallest axis | "
             "head-on 30/40/44° move at | axis correct | diagonal correct |", "|---|---|---|---|---|---|"]
    for name, r in report.items():
        agent = r.get("agent")
        cell = lambda key: (f"{agent[key]['mean']:.0%}" if agent and key in agent else "–")
        lines.append(f"| {r['label']} | {', '.join(f'{v:.0f}' for v in r['data']['positives_mean'])} | "
                     f"{r['data']['diagonal_to_axis_of_means']:.2f} | "
                     f"{' / '.join(f'{v:.0f}°' for v in r['data']['head_on_30_40_44'])} | "
                     f"{cell('axis')} | {cell('diagonal')} |")
    (args.out / "sweep.md").write_text("\n".join(lines) + "\n")
    plot(report, args.out / "sweep.png")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
