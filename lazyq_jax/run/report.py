"""``python -m lazyq_jax report``: results tables from run directories (trains nothing).

Rows are the methods (lazy Q's also named by the policy settings ``evaluate --set``
evaluated it with, as :func:`~lazyq_jax.run.results.method_label` does) x the settings
that differ between the runs: runs that agree on every setting but ``seed`` and
``parallel`` pool their seeds (a seed in two of them is an error: which would count?),
the others give rows of their own, labelled with the settings that differ.  Columns: the
task's rates as mean [95 % CI] over the seeds (:func:`lazyq_jax.stats.t_interval`, as in
``results.json``), the seeds, the budget and the training seconds per seed.  ``paired``:
each row's paired difference to the first row over the seeds both have (the seeds share
datasets and evaluation episodes); ``per_goal``: protocol A's episodes per goal direction
(push and arm), summed over the seeds.

Report blocks: in Markdown, the lines between ``<!-- report ARGS -->`` and
``<!-- /report -->`` are what ``report ARGS`` writes, its run directories relative to the
Markdown file's git root (the repository's root; the cwd outside a git repository), so
that :func:`blocks` checks or rewrites them.  :func:`archive` copies the small JSON files
a table needs (never checkpoints, data or figures) for committing under ``results/``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import re
import shlex
import shutil
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from lazyq_jax import tasks
from lazyq_jax.config import ConfigError, to_dict
from lazyq_jax.run.results import CI, method_label
from lazyq_jax.run.rundir import RunDirError, config_diff, lookup, parse_method
from lazyq_jax.run import suite
from lazyq_jax.run.runner import open_existing
from lazyq_jax.stats import format_ci, t_interval

NOT_COMPARED = ("seed", "parallel")  # what runs pooled into one row may differ in
LAZY_ONLY = ("train", "neighbours")  # run-config sections only lazy Q reads (a baseline: its method.json)
ARCHIVED = ("run.json", "results.json", "*/method.json", "*/timings.json", "*/eval.json")
BLOCK = re.compile(r"^<!-- report (.*?) -->\n(.*?)^<!-- /report -->", re.DOTALL | re.MULTILINE)
OUTCOMES = ("correct", "wrong", "not_pushed")


@dataclasses.dataclass
class Row:
    """A method under one set of settings (those that differ between the runs, and the
    policy settings it was evaluated with), its seeds pooled over the runs."""

    method: str
    settings: dict
    acting: dict
    seeds: dict = dataclasses.field(default_factory=dict)  # seed -> its results, train_s, run
    budgets: list = dataclasses.field(default_factory=list)

    @property
    def label(self) -> str:
        return method_label(self.method, self.settings)


def _read(run_dir: Path) -> tuple[dict, dict]:
    """A finished run's config (read back as the runner reads it) and ``results.json``."""
    if not (run_dir / "results.json").is_file():
        raise RunDirError(f"{run_dir}: no results.json (not a run directory, or its run has not been "
                          "evaluated yet: finish it with train/study --resume, or evaluate it)")
    return to_dict(open_existing(run_dir)[0]), json.loads((run_dir / "results.json").read_text())


def _budget(run_dir: Path, method: str, config: dict, timings: dict) -> str:
    """A method's training budget as its ``method.json`` (and ``run.json``) state it."""
    path = run_dir / parse_method(method).dirname / "method.json"
    record = json.loads(path.read_text()) if path.exists() else {}
    if record.get("method") == "lazy":
        t = record["train"]
        cycles = f"{config['train']['cycles']} cycles x {t['epochs']} epochs"
        return f"{timings['steps']} steps x {t['batch_size']} ({cycles})" if timings.get("steps") else cycles
    c = record.get("config", {})
    if "steps" not in c:
        return "–"
    return f"{c['steps']} steps x {c['batch_size']}" + (
        f" ({record['budget']:g} x lazy Q's)" if record.get("budget", 1) != 1 else "")


def gather(run_dirs: Sequence[Path], methods: Sequence[str] | None = None,
           root: Path = Path(".")) -> tuple[tasks.Task, list[Row]]:
    """The task and the rows (module docstring) of the runs in ``run_dirs`` (relative to
    ``root``), of ``methods`` (default: every method of the runs, in their order)."""
    runs = [(Path(d), *_read(root / d)) for d in run_dirs]
    kinds = {r["task"] for _, _, r in runs}
    if len(kinds) > 1:
        raise RunDirError("the runs are of different tasks (" + ", ".join(f"{d}: {r['task']}" for d, _, r in runs)
                          + "); one table per task")
    first = runs[0][1]
    differ = sorted({f for _, c, _ in runs[1:] for f in config_diff(first, c)
                     if f.split(".")[0] not in NOT_COMPARED})
    found = list(dict.fromkeys(m for _, _, r in runs for m in r["methods"]))
    unknown = [m for m in methods or () if m not in found]
    if unknown:
        raise RunDirError(f"{', '.join(unknown)}: in none of the runs; their methods: {', '.join(found)}")
    order = list(methods or found)
    # A baseline's row differs by its own config (method.json; what it took of train.* is
    # there), not by lazy Q's sections of the run config.
    own = {name: _method_configs(root, runs, name) for name in order if parse_method(name).name != "lazy"}
    own_differ = {name: sorted({f for c in cs.values() for f in config_diff(next(iter(cs.values())), c)})
                  for name, cs in own.items()}
    rows: dict[str, Row] = {}
    for d, config, results in runs:
        for name in order:
            m = results["methods"].get(name)
            if m is None:
                continue
            acting = m.get("acting", {})
            if name in own:
                settings = {**{f: lookup(config, f)[1] for f in differ if f.split(".")[0] not in LAZY_ONLY},
                            **{f: lookup(own[name][d], f)[1] for f in own_differ[name]}, **acting}
            else:
                settings = {**{f: lookup(config, f)[1] for f in differ}, **acting}
            row = rows.setdefault(json.dumps([name, settings], sort_keys=True), Row(name, settings, acting))
            t = m.get("timings", {})
            spent = (t["train_s"] + t.get("prepare_s", 0.0)) / len(results["seeds"]) if t.get("train_s") else None
            for seed_row in m["per_seed"]:
                seed = seed_row["seed"]
                if seed in row.seeds:
                    raise RunDirError(f"{row.label}: seed {seed} is in {row.seeds[seed]['run']} and in {d}: "
                                      "which would count? Name each seed's run once")
                row.seeds[seed] = {**seed_row, "train_s": spent, "run": str(d)}
            budget = _budget(root / d, name, config, t)
            row.budgets += [] if budget in row.budgets else [budget]
    return tasks.get(kinds.pop()), sorted(rows.values(), key=lambda row: order.index(row.method))


def _method_configs(root: Path, runs, name: str) -> dict:
    """``{run_dir: config}`` of method ``name``'s ``method.json`` in each run that has it."""
    out = {}
    for d, _, results in runs:
        path = root / d / parse_method(name).dirname / "method.json"
        if name in results["methods"] and path.is_file():
            out[d] = json.loads(path.read_text()).get("config", {})
    return out


def _interval(values: list, bounds: tuple[float, float] | None = (0.0, 1.0)) -> dict | None:
    """:func:`t_interval` of ``values``, or None where a seed lacks the number."""
    ok = values and all(isinstance(v, (int, float)) and math.isfinite(v) for v in values)
    return t_interval(values, bounds=bounds) if ok else None


def _outcomes(root: Path, row: Row) -> dict[str, list[int]]:
    """``goal in degrees -> [correct, wrong, not pushed]`` over the row's seeds (their ``eval.json``)."""
    table: dict[str, list[int]] = {}
    for run in dict.fromkeys(s["run"] for s in row.seeds.values()):
        path = root / run / parse_method(row.method).dirname / "eval.json"
        if not path.exists():
            raise RunDirError(f"{path}: missing; --per-goal reads each run's eval.json (evaluate the run)")
        stored = json.loads(path.read_text())
        if stored.get("acting", {}) != row.acting:
            raise RunDirError(f"{path} was evaluated with {stored.get('acting', {})}, its results.json row with "
                              f"{row.acting}: evaluate the run again")
        for seed in stored["per_seed"]:
            if row.seeds.get(seed["seed"], {}).get("run") == run:
                for g in seed["protocol_a"]["per_goal"]:
                    cell = table.setdefault(f"{math.degrees(g['goal']):.1f}", [0] * len(OUTCOMES))
                    cell[:] = [c + int(g[k]) for c, k in zip(cell, OUTCOMES)]
    return table


def command(args: argparse.Namespace) -> str:
    """The ``report`` command line that writes the table of ``args``."""
    return " ".join(["python -m lazyq_jax report", *(shlex.quote(str(d)) for d in args.run_dirs)]
                    + ([f"--methods {','.join(args.methods)}"] if args.methods else [])
                    + (["--paired"] if args.paired else []) + (["--per-goal"] if args.per_goal else []))


def table(args: argparse.Namespace, root: Path = Path(".")) -> dict:
    """The table of ``args`` (:func:`arguments`) as data: the ``--format json`` output."""
    if not args.run_dirs:
        raise RunDirError("name at least one run directory")
    task, rows = gather(args.run_dirs, args.methods, root)
    data = {"task": task.name, "rates": [list(r) for r in task.rates], "ci": CI, "command": command(args),
            "rows": []}
    for row in rows:
        seeds = sorted(row.seeds)
        spent = [row.seeds[s]["train_s"] for s in seeds]
        data["rows"].append({
            "label": row.label, "method": row.method, "settings": row.settings, "seeds": seeds,
            "runs": list(dict.fromkeys(row.seeds[s]["run"] for s in seeds)),
            "rates": {k: _interval([row.seeds[s].get(k) for s in seeds]) for k, _ in task.rates},
            "per_seed": {k: [row.seeds[s].get(k) for s in seeds] for k, _ in task.rates},
            "budget": " / ".join(row.budgets),
            "train_s_per_seed": None if None in spent else float(np.mean(spent))})
    if args.paired:
        ref = rows[0]
        data["paired"] = []
        for row in rows[1:]:
            common = sorted(set(ref.seeds) & set(row.seeds))
            pairs = {k: [(row.seeds[s].get(k), ref.seeds[s].get(k)) for s in common] for k, _ in task.rates}
            data["paired"].append({"label": row.label, "reference": ref.label, "seeds": common, "differences": {
                k: _interval([a - b if None not in (a, b) else None for a, b in p], bounds=None)
                for k, p in pairs.items()}})
    if args.per_goal:
        if not task.directions:
            raise RunDirError(f"--per-goal: task {task.name} has no goal directions (protocol A)")
        data["per_goal"] = {row.label: _outcomes(root, row) for row in rows}
    return data


def markdown(data: dict) -> str:
    """The Markdown of a :func:`table`: the table, a line naming what it shows and the command
    that writes it, then the paired differences and the outcomes per goal, if asked for."""
    keys, labels = zip(*data["rates"])
    head = lambda first, cols: [f"| {first} | " + " | ".join(cols) + " |", "|---" * (len(cols) + 1) + "|"]
    lines = head("method", [*labels, "seeds", "budget", "train s / seed"])
    for row in data["rows"]:
        spent = row["train_s_per_seed"]
        lines.append(f"| {row['label']} | " + " | ".join(format_ci(row["rates"][k]) if row["rates"][k] else "–"
                                                       for k in keys)
                     + f" | {len(row['seeds'])} | {row['budget']} | {'–' if spent is None else f'{spent:.0f}'} |")
    seeds = {tuple(r["seeds"]) for r in data["rows"]}
    which = (", ".join(map(str, data["rows"][0]["seeds"])) if len(seeds) == 1 else
             "; ".join(f"{r['label']} {', '.join(map(str, r['seeds']))}" for r in data["rows"]))
    lines += ["", (f"Task {data['task']}, seeds {which}; mean [{data['ci']}]; budget: gradient steps x batch "
                   "size as the runs state it; train s / seed: a run's training and neighbour-search seconds "
                   f"over its seeds.  Written by `{data['command']}`.")]
    if "paired" in data:
        lines += ["", (f"Paired differences to {data['rows'][0]['label']} over the seeds both rows have "
                       "(percentage points, mean [95 % Student-t interval]):"), "", *head("method", [*labels, "seeds"])]
        for p in data["paired"]:
            cells = [format_ci(d).replace(" %", "") if d else "–" for d in p["differences"].values()]
            lines.append(f"| {p['label']} | " + " | ".join(cells) + f" | {len(p['seeds'])} |")
    if "per_goal" in data:
        goals = sorted({g for t in data["per_goal"].values() for g in t}, key=float)
        cell = lambda c: " / ".join(map(str, c)) if c else "–"
        lines += ["", ("Protocol A's episodes per goal direction, summed over each row's seeds: correct / wrong "
                       "direction / not pushed:"), "", *head("goal (deg)", list(data["per_goal"]))]
        lines += [f"| {g} | " + " | ".join(cell(t.get(g)) for t in data["per_goal"].values()) + " |" for g in goals]
        lines.append("| all | " + " | ".join(cell(np.sum(list(t.values()), axis=0).tolist())
                                            for t in data["per_goal"].values()) + " |")
    return "\n".join(lines) + "\n"


def render(args: argparse.Namespace, root: Path = Path("."), fmt: str = "md") -> str:
    if args.suite:  # a benchmark directory's table (lazyq_jax.run.suite)
        data = suite.table(root / args.suite, command=f"python -m lazyq_jax report --suite {args.suite}")
        return suite.markdown(data) if fmt == "md" else json.dumps(data, indent=1) + "\n"
    data = table(args, root)
    return markdown(data) if fmt == "md" else json.dumps(data, indent=1) + "\n"


class _BlockParser(argparse.ArgumentParser):
    def error(self, message):
        raise RunDirError(f"report arguments: {message}")


def arguments(p: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    """The arguments a table is made of (the CLI's and a report block's)."""
    p = p or _BlockParser(prog="report", add_help=False)
    p.add_argument("run_dirs", nargs="*", type=Path, metavar="RUN_DIR",
                   help="run directories (of train, study or evaluate, or report --archive copies)")
    p.add_argument("--methods", type=lambda s: [m.strip() for m in s.split(",") if m.strip()],
                   help="comma-separated methods as in results.json, in the table's order (default: all)")
    p.add_argument("--paired", action="store_true",
                   help="each row's paired difference to the first row over the seeds both have")
    p.add_argument("--per-goal", action="store_true",
                   help="protocol A's episodes per goal direction (push, arm): correct / wrong / not pushed")
    p.add_argument("--suite", type=Path, metavar="DIR", default=None,
                   help="a benchmark directory's table (python -m lazyq_jax benchmark; or its report "
                   "--archive copy): each dataset's success per method beside the published numbers")
    return p


def git_root(path: Path) -> Path:
    """The root of the git repository holding ``path`` (the cwd outside one)."""
    return next((p for p in Path(path).resolve().parents if (p / ".git").exists()), Path.cwd())


def _block(m: re.Match, path: Path, text: str, differ: list, errors: list, update: bool) -> str:
    """One report block regenerated (left as it is where it cannot be), ``differ``/``errors`` told."""
    where = f"{path}:{text.count(chr(10), 0, m.start()) + 1}: <!-- report {m[1]} -->"
    try:
        new = render(arguments().parse_args(shlex.split(m[1])), git_root(path))
    except (ConfigError, RunDirError, OSError, ValueError) as e:
        errors.append(f"{where}: {e}")
        return m[0]
    if new != m[2]:
        differ.append(f"{where}: differs from what its runs give" + ("; rewritten" if update else ""))
    return f"<!-- report {m[1]} -->\n{new}<!-- /report -->"


def blocks(files: Sequence[Path], update: bool = False) -> tuple[list[str], list[str]]:
    """``(differ, errors)``: the report blocks of the Markdown ``files`` that differ from what
    their runs give, and those that cannot be regenerated (e.g. their runs are missing),
    each as ``file:line: <!-- report ARGS -->: why``; ``update``: rewrite those that differ."""
    missing = [str(f) for f in files if not Path(f).is_file()]
    if missing:
        raise RunDirError(f"no such Markdown file: {', '.join(missing)}")
    differ, errors = [], []
    for path in map(Path, files):
        text = path.read_text()
        new_text = BLOCK.sub(lambda m, p=path, t=text: _block(m, p, t, differ, errors, update), text)
        if update and new_text != text:
            path.write_text(new_text)
    return differ, errors


def archive(dest: Path, run_dir: Path) -> list[Path]:
    """Copy what :func:`table` reads of ``run_dir`` (:data:`ARCHIVED`: run.json, results.json,
    each method's method.json, timings.json and eval.json) into ``dest``; returns the copies.
    A benchmark directory (``suite.json``): its own table files and each finished dataset's
    seed groups."""
    if (run_dir / suite.SUITE_FILE).is_file():
        copies = []
        for name in (suite.SUITE_FILE, "results.json", "results.md"):
            if (run_dir / name).is_file():
                dest.mkdir(parents=True, exist_ok=True)
                copies.append(dest / name)
                shutil.copyfile(run_dir / name, copies[-1])
        meta = suite.read_suite(run_dir)
        groups = suite.seed_groups(meta)
        for name in meta["datasets"]:
            for group in groups:  # each seed group's run directory (suite.group_dir)
                rel = suite.group_dir(Path(name), group, groups)
                if (run_dir / rel / "results.json").is_file():
                    copies += archive(dest / rel, run_dir / rel)
        return copies
    _read(run_dir)
    copies = []
    for pattern in ARCHIVED:
        for src in sorted(run_dir.glob(pattern)):
            copies.append(dest / src.relative_to(run_dir))
            copies[-1].parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(src, copies[-1])
    return copies
