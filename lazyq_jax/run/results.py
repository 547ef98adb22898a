"""A run's results: per seed and mean with a 95 % confidence interval over the seeds
(:func:`lazyq_jax.stats.t_interval`), ``results.json``, ``summary.md`` and the comparison
figures."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from lazyq_jax import plots
from lazyq_jax.run.rundir import RUN_VERSION, write_json
from lazyq_jax.stats import format_ci, t_interval
from lazyq_jax.tasks import Task

CI = "95 % Student-t interval over seeds (clipped to [0, 1])"


def method_summary(task: Task, per_seed_eval: list[dict]) -> dict:
    """``{"per_seed": [...], "summary": {rate: {mean, ci95, sd, n}}, "per_direction": [...]}``."""
    rows = [{"seed": r["seed"], **task.seed_rates(r)} for r in per_seed_eval]
    names = [key for key in rows[0] if key not in ("seed", "per_direction_correct_rate")
             and isinstance(rows[0][key], float)]
    summary = {name: t_interval([row[name] for row in rows]) for name in names
               if all(np.isfinite(row.get(name, np.nan)) for row in rows)}
    out = {"per_seed": rows, "summary": summary}
    if task.directions:
        goals = [row["goal"] for row in per_seed_eval[0]["protocol_a"]["per_goal"]]
        out["per_direction"] = [
            {"goal": g, **t_interval([row["per_direction_correct_rate"][i] for row in rows])}
            for i, g in enumerate(goals)]
    return out


def earlier_methods(run_dir: Path, seeds) -> dict:
    """The method rows of the run's ``results.json`` (same seeds), in their order: a resume
    with a subset of the methods replaces their rows and keeps the others'."""
    path = run_dir / "results.json"
    if not path.exists():
        return {}
    old = json.loads(path.read_text())
    if old.get("version") != RUN_VERSION or old.get("seeds") != list(seeds):
        return {}
    return old.get("methods", {})


def write_results(task: Task, run_dir: Path, seeds, summaries: list[dict], methods: dict[str, dict],
                  earlier: dict | None = None) -> dict:
    """``results.json``, ``summary.md`` and the comparison figures for ``methods`` (``{spec:
    {"per_seed_eval", "timings"}}``) merged into the ``earlier`` rows (their order kept, the
    new methods after them)."""
    rows = {name: {**method_summary(task, m["per_seed_eval"]), "timings": m["timings"],
                   **({"acting": m["acting"]} if m.get("acting") else {})}
            for name, m in methods.items()}
    merged = {name: rows.get(name, old) for name, old in (earlier or {}).items()}
    results = {"version": RUN_VERSION, "task": task.name, "seeds": list(seeds), "ci": CI,
               "data": task.data_table(summaries), "methods": {**merged, **rows}}
    write_json(run_dir / "results.json", results)
    text = summary_markdown(task, results)
    if text:
        (run_dir / "summary.md").write_text(text)
    figures = run_dir / "figures"
    if task.directions:
        plots.study_per_direction(results, figures / "per_direction.png")
    if len(results["methods"]) > 1:
        plots.study_methods(results, task.rates, figures / "methods.png")
    return results


def method_label(text: str, acting: dict | None) -> str:
    """A method's name in logs and summaries, with the policy settings it was evaluated with
    where they are not its run's, e.g. ``lazy (neighbours.subgoal_steps=0)``."""
    return f"{text} ({', '.join(f'{k}={v}' for k, v in acting.items())})" if acting else text


def summary_markdown(task: Task, results: dict) -> str:
    seeds = results["seeds"]
    keys = [(k, label) for k, label in task.rates
            if any(k in m["summary"] or len(seeds) == 1 for m in results["methods"].values())]
    lines = [f"Task {task.name}; {len(seeds)} seed{'s' if len(seeds) > 1 else ''} "
             f"({', '.join(map(str, seeds))}); " + (f"mean [{results['ci']}]." if len(seeds) > 1
                                                     else "one seed (no interval)."), "",
             "| method | " + " | ".join(label for _, label in keys) + " | training |",
             "|---|" + "---|" * len(keys) + "---|"]
    for name, m in results["methods"].items():
        cell = lambda key: format_ci(m["summary"][key]) if key in m["summary"] else "–"
        t = m["timings"]
        train = (f"{t['train_s']:.0f} s" if t.get("train_s") else "–") + (
            f" ({t['steps_per_s']:.0f} steps/s)" if t.get("steps_per_s") else "")
        cells = " | ".join(cell(k) for k, _ in keys)
        lines.append(f"| {method_label(name, m.get('acting'))} | {cells} | {train} |")
    return "\n".join(lines) + "\n"
