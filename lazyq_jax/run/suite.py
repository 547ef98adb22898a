"""A benchmark suite's table: one run directory per dataset under one suite directory, each
dataset's success per method as mean [95 % CI] over the seeds beside the published numbers,
and each method's budget as a share of the published one.

``SUITE_DIR/suite.json`` (written by ``benchmark``) names the suite, its datasets (in order),
methods, seeds and seed groups (the seeds trained together, :func:`seed_groups`);
``SUITE_DIR/<dataset>/`` is an ordinary run directory (``results.json``, ``run.json``, each
method's ``method.json`` and ``timings.json``) holding the first group, each later group one
below it (:func:`group_dir`), so ``report --archive`` copies work as well as live runs.  A
dataset's row pools the seeds of its groups that have a ``results.json``; datasets with none
yet are listed as pending.  The rate is the task's first (:attr:`~lazyq_jax.tasks.base.Task.rates`), the
published numbers the task's (:attr:`~lazyq_jax.tasks.base.Task.published`).  A method
re-evaluated with other policy settings (``evaluate --set``: its results' ``acting``) is
labelled with them, in its column's head where every dataset has the same, else in its cells;
seed groups of one dataset evaluated differently are refused.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Sequence

from lazyq_jax import tasks
from lazyq_jax.run.results import CI, method_label
from lazyq_jax.run.rundir import RunDirError, parse_method, write_json
from lazyq_jax.stats import format_ci, t_interval

SUITE_FILE = "suite.json"


def read_suite(suite_dir: Path) -> dict:
    """``suite.json`` of ``suite_dir`` (:class:`RunDirError` saying what is wrong)."""
    path = Path(suite_dir) / SUITE_FILE
    if not path.is_file():
        raise RunDirError(f"{suite_dir}: no {SUITE_FILE} (not a benchmark directory: make one with "
                          "python -m lazyq_jax benchmark SUITE --run-dir DIR)")
    return json.loads(path.read_text())


def seed_groups(meta: dict) -> list[list[int]]:
    """The seed groups of a ``suite.json`` (a benchmark of an older lazyq-jax: one, its seeds)."""
    return [list(g) for g in meta.get("seed_groups") or [meta["seeds"]]]


def group_dir(dataset_dir: Path, group: Sequence[int], groups: Sequence[Sequence[int]]) -> Path:
    """The run directory of seed ``group`` (one of ``groups``): the dataset's own directory for
    the first group, ``seeds-<s1>-<s2>...`` below it for each later one."""
    if list(group) == list(groups[0]):
        return Path(dataset_dir)
    return Path(dataset_dir) / ("seeds-" + "-".join(str(s) for s in group))


def _steps(method_dir: Path, timings: dict) -> tuple[int, int] | None:
    """``(gradient steps, batch size)`` of a trained method, as its records state them."""
    record = json.loads((method_dir / "method.json").read_text()) if (method_dir / "method.json").exists() else {}
    batch = (record.get("train") or record.get("config") or {}).get("batch_size")
    steps = timings.get("steps") or (record.get("config") or {}).get("steps")
    return (int(steps), int(batch)) if steps and batch else None


def _method(runs: Sequence[tuple[Path, dict]], name: str, key: str) -> dict | None:
    """Method ``name``'s entry pooled over the seed groups ``runs`` (``(run_dir, results)``)."""
    rows, seconds, steps, acting = [], [], [], {}
    for run_dir, results in runs:
        m = results["methods"].get(name)
        if m is None:
            continue
        if rows and m.get("acting", {}) != acting:
            raise RunDirError(f"{run_dir}: {name} was evaluated with the policy settings {m.get('acting', {})}, "
                              f"its other seeds with {acting}: evaluate every seed group alike "
                              "(python -m lazyq_jax evaluate --run-dir DIR --set ...)")
        acting = m.get("acting", {})
        rows += m["per_seed"]
        timings = m.get("timings", {})
        seconds.append((timings["train_s"] + timings.get("prepare_s", 0.0)) if timings.get("train_s") else None)
        steps.append(_steps(run_dir / parse_method(name).dirname, timings))
    if not rows:
        return None
    values = [row.get(key) for row in rows]
    ok = all(isinstance(v, (int, float)) and math.isfinite(v) for v in values)
    return {"rate": t_interval(values, bounds=(0.0, 1.0)) if ok else None,
            "seeds": [row["seed"] for row in rows], "acting": acting,
            "steps": steps[0] if len(set(steps)) == 1 else None,
            "train_s_per_seed": sum(seconds) / len(rows) if None not in seconds else None}


def table(suite_dir: Path, command: str | None = None) -> dict:
    """The suite's table as data (``results.json`` of a benchmark directory)."""
    suite_dir = Path(suite_dir)
    meta = read_suite(suite_dir)
    methods = list(meta["methods"])
    groups = seed_groups(meta)
    out = {"suite": meta["suite"], "ci": CI, "rate_label": "", "methods": methods, "seeds": meta["seeds"],
           "command": command or meta.get("command", ""), "datasets": []}
    for name in meta["datasets"]:
        task = tasks.get(name)
        key = task.rates[0][0]
        out["rate_label"] = out["rate_label"] or dict(task.rates).get(key, key)
        entry = {"dataset": name, "rate": key, "published": {m: list(v) for m, v in task.published.items()},
                 "published_source": task.published_source,
                 "published_budget": list(task.published_budget) if task.published_budget else None,
                 "methods": {}, "pending": True}
        run_dir = suite_dir / name
        if (run_dir / "run.json").is_file():
            entry["eval"] = json.loads((run_dir / "run.json").read_text())["config"].get("eval")
        runs = [(d, json.loads((d / "results.json").read_text()))
                for d in (group_dir(run_dir, g, groups) for g in groups) if (d / "results.json").is_file()]
        if runs:
            entry["pending"] = False
            entry["methods"] = {m: _method(runs, m, key) for m in methods}
        out["datasets"].append(entry)
    return out


def write(suite_dir: Path, command: str | None = None) -> dict:
    """``results.json`` and ``results.md`` of the suite directory (its table now)."""
    data = table(suite_dir, command)
    write_json(Path(suite_dir) / "results.json", data)
    (Path(suite_dir) / "results.md").write_text(markdown(data))
    return data


def _published(p) -> str:
    mean, std = p
    return f"{mean:g}" + ("" if std is None else f" ± {std:g}")


def markdown(data: dict) -> str:
    """The suite's Markdown: one row per dataset, a column per method (mean [95 % CI] over the
    seeds, OGBench's published mean in parentheses), the best published number; under it the
    budgets as shares of the published budget and the command."""
    methods = data["methods"]
    actings = {m: {json.dumps(d["methods"][m].get("acting", {}), sort_keys=True) for d in data["datasets"]
                   if not d["pending"] and d["methods"].get(m)} for m in methods}
    shared = {m: json.loads(a.pop()) if len(a) == 1 else None for m, a in actings.items()}
    heads = [method_label(m, shared[m]) for m in methods]
    lines = ["| dataset | " + " | ".join(heads) + " | best published |", "|---" * (len(methods) + 2) + "|"]
    budgets: dict[str, set] = {m: set() for m in methods}
    shares: dict[str, set] = {m: set() for m in methods}
    for d in data["datasets"]:
        cells = []
        for m in methods:
            r = None if d["pending"] else d["methods"].get(m)
            ours = "pending" if d["pending"] else ("–" if not r or not r["rate"] else format_ci(r["rate"]))
            n = len(r["seeds"]) if r and r["rate"] else 0
            if n and (n == 1 or n < len(data["seeds"])):  # fewer seeds than the suite's: said in the cell
                ours += f" ({n} seed{'s' if n > 1 else ''})"
            if r and shared[m] is None and r.get("acting"):  # the column's datasets differ
                ours += method_label("", r["acting"])
            pub = d["published"].get(parse_method(m).name)
            cells.append(ours + ("" if pub is None else f" ({pub[0]:g})"))
            if r and r["steps"]:
                steps, batch = r["steps"]
                budgets[m].add(f"{steps:,} x {batch}")
                if d["published_budget"]:
                    p_steps, p_batch = d["published_budget"]
                    shares[m].add(f"{100 * steps * batch / (p_steps * p_batch):.0f} %")
        best = max(d["published"].items(), key=lambda kv: kv[1][0], default=None)
        best_text = "–" if best is None else f"{best[0].upper()} {_published(best[1])}"
        lines.append(f"| {d['dataset']} | " + " | ".join(cells) + f" | {best_text} |")
    seeds = ", ".join(map(str, data["seeds"]))
    source = next((d["published_source"] for d in data["datasets"] if d["published_source"]), "")
    p_budget = next((d["published_budget"] for d in data["datasets"] if d["published_budget"]), None)
    budget = "; ".join(f"{m} {' / '.join(sorted(budgets[m]))} ({' / '.join(sorted(shares[m]))} of the "
                       "published rows)" for m in methods if budgets[m])
    evals = {json.dumps(d.get("eval"), sort_keys=True) for d in data["datasets"] if d.get("eval")}
    protocol = ("; evaluation: " + ", ".join(f"{k} {v}" for k, v in json.loads(evals.pop()).items() if k != "seed")
                if len(evals) == 1 else "; evaluation: each dataset's (its run.json)")
    label = data.get("rate_label") or "success"
    lines += ["", f"{label[:1].upper() + label[1:]} per dataset, seeds {seeds}: mean "
              f"[{data['ci']}]{protocol}.  In parentheses the method's published mean; best published: "
              f"the highest published mean ± std ({source or 'none'}"
              + (f"; published budget {p_budget[0]:,} steps x {p_budget[1]}" if p_budget else "") + ").  Budget (gradient "
              f"steps x batch): {budget or '–'}.  Written by `{data['command']}`."]
    return "\n".join(lines) + "\n"
