"""Studies: the whole pipeline for many seeds, each phase one program over all seeds.

A study of seeds ``s_1 .. s_S`` is ``S`` independent replicates of a run: seed ``s``
has its own dataset, neighbourhood samples, initialisation and evaluation episodes
(``config.seed = eval.seed = s``), and equals ``python -m lazyq_jax train --set
seed=s --set eval.seed=s`` up to the floating-point chaos of training (datasets and
neighbourhoods are bitwise the same; tests/test_study.py says how the rest is
checked).  How the seeds share the machine:

* collection: one compiled MJX kernel, called for every seed's episodes;
* neighbour search: every seed's grid over the same bounds and padded to the same
  size, so the compiled passes are shared (no recompilation per seed);
* training: the datasets padded to a common length and stacked, and
  ``jax.vmap(Trainer.run_cycle)`` over the seeds' states, datasets and
  neighbourhoods (:mod:`lazyq_jax.train` ignores each seed's padding);
* evaluation: the seeds' lazy policies stacked, both protocols ``vmap``-ed.

Layout of a study directory::

    study.json                      config, seeds, version (a resume must match it)
    seeds/<seed>/dataset.npz        each seed's dataset (+ dataset_summary.json)
    <method>/checkpoints/<cycle>/   the seeds' training states, stacked (orbax)
    <method>/metrics.jsonl          per cycle: every metric as a list over the seeds
    <method>/eval.json              per seed: both protocols (as eval/results.json of a run)
    results.json, summary.md        per seed and mean with 95 % CI (:mod:`lazyq_jax.stats`)
    figures/per_direction.png       correct rate per goal direction with CI bars

Everything is resumable: datasets, checkpoints and evaluations that exist are reused.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import time
import zlib
from pathlib import Path
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp
from tqdm.auto import tqdm

from lazyq_jax import baselines
from lazyq_jax.checkpoint import load_latest_intact, save_checkpoint
from lazyq_jax.config import Config, ConfigError, from_dict, override, to_dict
from lazyq_jax.data import dataset_summary
from lazyq_jax.env.scripted import scripted_push_policy
from lazyq_jax.evaluate import direction_rates, evaluate_stacked, policy_act
from lazyq_jax.neighbours import build_index
from lazyq_jax.parallel import over_seeds
from lazyq_jax.pipeline import RunDirError, neighbours_for, prepare_dataset, run_keys, state_bounds
from lazyq_jax.policy import LazyPolicy
from lazyq_jax.stats import format_ci, t_interval
from lazyq_jax.targets import bootstrap_table
from lazyq_jax.train import make_train_for
from lazyq_jax.types import Transitions, pad_transitions

STUDY_VERSION = 1
METHODS = ("lazy", *baselines.METHODS, "random", "scripted")
# The rates a study reports per seed and as mean +- CI (the last one is protocol B's).
RATES = ("axis_correct_rate", "diagonal_correct_rate", "overall_correct_rate",
         "long_horizon_success_rate")


def _log(msg: str) -> None:
    tqdm.write(msg)


def seed_config(config: Config, seed: int) -> Config:
    """The run config of one of a study's seeds: ``seed`` for everything, evaluation too."""
    return dataclasses.replace(config, seed=int(seed), eval=dataclasses.replace(config.eval,
                                                                                seed=int(seed)))


def check_seeds(seeds: Sequence[int]) -> tuple[int, ...]:
    seeds = tuple(seeds)
    if not seeds:
        raise ConfigError("a study needs at least one seed (--seeds N)")
    if any(not isinstance(s, (int, np.integer)) or isinstance(s, bool) or s < 0 for s in seeds):
        raise ConfigError(f"seeds must be integers >= 0, got {list(seeds)}")
    if len(set(seeds)) != len(seeds):
        raise ConfigError(f"seeds must be distinct, got {list(seeds)}")
    return tuple(int(s) for s in seeds)


def parse_method(spec: str) -> tuple[str, dict[str, str]]:
    """``"iql:temperature=10:budget=4"`` -> ``("iql", {"temperature": "10", "budget": "4"})``.

    A method is one of :data:`METHODS`; a baseline may carry overrides of its config
    fields and ``budget`` (a multiple of lazy Q's gradient steps).
    """
    name, *parts = spec.strip().split(":")
    if name not in METHODS:
        raise ConfigError(f"unknown method {name!r} in {spec!r}; choose from {list(METHODS)}")
    fields = {}
    for part in parts:
        if "=" not in part:
            raise ConfigError(f"method option {part!r} in {spec!r} must look like field=value")
        key, value = part.split("=", 1)
        fields[key.strip()] = value.strip()
    if fields and name in ("lazy", "random", "scripted"):
        raise ConfigError(f"{spec!r}: {name} takes no options (set lazy Q's with --set)")
    return name, fields


def check_methods(methods: Sequence[str]) -> tuple[str, ...]:
    methods = tuple(m.strip() for m in methods)
    if not methods:
        raise ConfigError(f"a study needs at least one method; choose from {list(METHODS)}")
    for m in methods:
        parse_method(m)
    if len(set(methods)) != len(methods):
        raise ConfigError(f"methods must be distinct, got {list(methods)}")
    return methods


# ----------------------------------------------------------------------------- data


@dataclasses.dataclass
class StudyData:
    """The seeds' datasets, unpadded and stacked (padded to the longest)."""

    seeds: tuple[int, ...]
    datasets: list[Transitions]
    stacked: Transitions  # leaves [S, N_max, ...]
    n_valid: jax.Array  # int32 [S]
    bounds: tuple[float, float, float, float]  # one grid for all seeds
    summaries: list[dict]

    @property
    def capacity(self) -> int:
        return int(self.stacked.r.shape[1])


def prepare_study_data(config: Config, run_dir: Path, seeds: Sequence[int],
                       progress: bool = True) -> StudyData:
    """Collect (or reuse) every seed's dataset; the collection kernel compiles once."""
    datasets, summaries = [], []
    for seed in tqdm(seeds, desc="datasets (seeds)", disable=not progress, leave=False):
        seed_dir = run_dir / "seeds" / str(seed)
        seed_dir.mkdir(parents=True, exist_ok=True)
        data = prepare_dataset(seed_config(config, seed), seed_dir, progress=False)
        datasets.append(data)
        summaries.append(dataset_summary(data, config.collect.n_goals))
    n_max = max(d.size for d in datasets)
    stacked = jax.tree.map(lambda *x: jnp.stack(x), *[pad_transitions(d, n_max) for d in datasets])
    all_s = np.concatenate([np.asarray(d.s) for d in datasets])
    return StudyData(tuple(seeds), datasets, stacked, jnp.asarray([d.size for d in datasets], jnp.int32),
                     state_bounds(config, all_s), summaries)


def stacked_neighbours(config: Config, sd: StudyData, cycle: int | None = None,
                       progress: bool = False) -> jax.Array:
    """``idx [S, N_max, k]``: every seed's neighbourhoods (rows past its size are 0).

    The grids share bounds and capacity, so the search passes compile once for all
    seeds; each seed's neighbourhoods equal those of its single run.
    """
    out = []
    for seed, data in zip(tqdm(sd.seeds, desc="neighbours (seeds)", disable=not progress,
                               leave=False), sd.datasets):
        padded = pad_transitions(data, sd.capacity)
        out.append(neighbours_for(seed_config(config, seed), padded, cycle, n_valid=data.size,
                                  bounds=sd.bounds))
    return jnp.stack(out)


# ----------------------------------------------------------------------------- lazy Q


def _metrics_record(cycle: int, seconds: float, metrics: dict) -> dict:
    return {"cycle": cycle, "seconds": round(seconds, 2),
            **{k: np.asarray(v).round(5).tolist() for k, v in metrics.items()}}


def train_lazy(config: Config, method_dir: Path, sd: StudyData, progress: bool = True):
    """Train lazy Q for all seeds at once (``vmap`` of ``run_cycle``), one checkpoint per
    cycle; resumes from the newest intact checkpoint.  Returns ``(states, trainer, timings)``
    with the seconds of this call's neighbour searches and training cycles."""
    tc = config.train
    ckpt_dir = method_dir / "checkpoints"
    metrics_path = method_dir / "metrics.jsonl"
    bar = tqdm(total=tc.cycles * tc.epochs, unit="epoch", desc="lazy: training (all seeds)",
               disable=not progress, leave=False)
    cycle_now = [0]

    def on_epoch(e):  # called once per seed and epoch under vmap: move the bar, never back
        target = cycle_now[0] * tc.epochs + int(e) + 1
        if target > bar.n:
            bar.update(target - bar.n)

    trainer = make_train_for(config, progress=on_epoch if progress else None)
    found = load_latest_intact(ckpt_dir, expect=config, seeds=sd.seeds, warn=_log) \
        if ckpt_dir.exists() else None
    if found is not None:
        state = found[0]
        first = int(np.asarray(state.cycle)[0])
        kept = [line for line in metrics_path.read_text().splitlines()
                if json.loads(line)["cycle"] <= first] if metrics_path.exists() else []
        metrics_path.write_text("".join(line + "\n" for line in kept))
        _log(f"lazy: resuming from cycle {first} of {tc.cycles}")
    else:
        keys = jnp.stack([run_keys(seed_config(config, s))["train"] for s in sd.seeds])
        state = over_seeds(trainer.init, len(sd.seeds))(keys)
        first = 0
        metrics_path.write_text("")
    timings = {"neighbours_s": 0.0, "train_s": 0.0}
    if first >= tc.cycles:
        bar.close()
        return state, trainer, timings
    resample = tc.resample_neighbours
    t = time.perf_counter()
    idx = jax.block_until_ready(stacked_neighbours(
        config, sd, first if resample and first > 0 else None, progress))
    timings["neighbours_s"] += time.perf_counter() - t
    run_cycle = over_seeds(trainer.run_cycle, len(sd.seeds))
    bar.update(first * tc.epochs)
    for cycle in range(first, tc.cycles):
        cycle_now[0] = cycle
        if resample and cycle > first:
            t = time.perf_counter()
            idx = jax.block_until_ready(stacked_neighbours(config, sd, cycle))
            timings["neighbours_s"] += time.perf_counter() - t
        t = time.perf_counter()
        state, metrics = run_cycle(state, sd.stacked, idx, sd.n_valid)
        metrics = jax.device_get(metrics)
        timings["train_s"] += time.perf_counter() - t
        save_checkpoint(ckpt_dir, state, config, seeds=sd.seeds)
        record = _metrics_record(cycle + 1, time.perf_counter() - t, metrics)
        with metrics_path.open("a") as f:
            f.write(json.dumps(record) + "\n")
        bar.update((cycle + 1) * tc.epochs - bar.n)
        loss = np.asarray(record["loss"])
        _log(f"lazy: cycle {cycle + 1:>2}/{tc.cycles}: loss {loss.mean():.4f} (seeds "
             f"{loss.min():.4f}-{loss.max():.4f})  clip {np.mean(record['clip_fraction']):.1%}  "
             f"({record['seconds']:.1f} s)")
    bar.close()
    return state, trainer, timings


def stacked_lazy_policy(config: Config, trainer, states, sd: StudyData) -> LazyPolicy:
    """The seeds' lazy policies (Eq. 9) stacked: grids over the same bounds, capacity and
    window, values ``r + gamma (1 - done) V_seed(s', g)`` of each seed's trained V."""
    nc, max_level = config.neighbours, config.eval.max_level
    indices = [build_index(d.s, d.g, k=nc.k, radius_s=nc.radius_s, radius_g=nc.radius_g,
                           growth=nc.growth, max_level=max_level, bounds=sd.bounds,
                           capacity=sd.capacity) for d in sd.datasets]
    window = max(index.max_window for index in indices)
    index = jax.tree.map(lambda *x: jnp.stack(x), *[i.replace(max_window=window) for i in indices])
    values = over_seeds(lambda st, d: bootstrap_table(trainer.value_fn(st), d, config.train.gamma),
                        len(sd.seeds))(states, sd.stacked)
    length = jnp.full(len(sd.seeds), config.collect.push.action_length, jnp.float32)
    return LazyPolicy(index, sd.stacked.a, values, length)


def run_lazy(config: Config, run_dir: Path, sd: StudyData, progress: bool = True) -> dict:
    """Train (or resume) and evaluate lazy Q for every seed; returns the method's record."""
    method_dir = run_dir / "lazy"
    method_dir.mkdir(parents=True, exist_ok=True)
    eval_path = method_dir / "eval.json"
    states, trainer, spent = train_lazy(config, method_dir, sd, progress)
    timing_path = method_dir / "timings.json"
    timings = json.loads(timing_path.read_text()) if timing_path.exists() else {}
    for name, seconds in spent.items():  # accumulated over resumed sessions
        timings[name] = round(timings.get(name, 0.0) + seconds, 1)
    if timings.get("train_s"):
        timings["steps"] = lazy_steps(config, sd)
        timings["steps_per_s"] = round(timings["steps"] * len(sd.seeds) / timings["train_s"], 1)
    timing_path.write_text(json.dumps(timings))
    if eval_path.exists():
        per_seed = json.loads(eval_path.read_text())
        if [r["seed"] for r in per_seed] == list(sd.seeds):
            return {"per_seed_eval": per_seed, "timings": timings}
    _log("lazy: evaluating all seeds (protocols A and B)")
    t = time.perf_counter()
    policies = stacked_lazy_policy(config, trainer, states, sd)
    per_seed, _, _ = evaluate_stacked(config.collect.push, config.eval, policy_act, policies,
                                      sd.seeds)
    timings["eval_s"] = round(time.perf_counter() - t, 1)
    eval_path.write_text(json.dumps(per_seed, indent=1))
    timing_path.write_text(json.dumps(timings))
    return {"per_seed_eval": per_seed, "timings": timings}


# ----------------------------------------------------------------------------- baselines


def lazy_steps(config: Config, sd: StudyData) -> int:
    """Lazy Q's gradient steps on the smallest of the seeds' datasets: the budget unit."""
    tc = config.train
    return tc.cycles * tc.epochs * (int(np.min(np.asarray(sd.n_valid))) // tc.batch_size)


def baseline_config(spec: str, config: Config, sd: StudyData):
    """The config of a baseline in a study: lazy Q's budget (gradient steps x ``budget``),
    batch size, network width and depth, discount and input scale; the method's own
    defaults otherwise, then the spec's overrides."""
    name, fields = parse_method(spec)
    fields = dict(fields)
    budget = float(fields.pop("budget", 1.0))
    if not budget > 0:
        raise ConfigError(f"{spec!r}: budget must be > 0")
    tc = config.train
    cls = baselines.config_class(name)
    cfg = cls(steps=max(1, round(budget * lazy_steps(config, sd))), batch_size=tc.batch_size,
              width=tc.width, depth=tc.depth, gamma=tc.gamma,
              state_scale=config.collect.start_range)
    cfg = override(cfg, [f"{k}={v}" for k, v in fields.items()])
    return cfg, budget


def _found(act):
    """An :data:`~lazyq_jax.evaluate.Act` (actions and found flags) of a plain policy."""
    return lambda key, s, g: (act(key, s, g), jnp.ones(s.shape[0], bool))


def _method_dir(run_dir: Path, spec: str) -> Path:
    return run_dir / "methods" / spec.replace(":", "__").replace("=", "-")


def run_baseline(spec: str, config: Config, run_dir: Path, sd: StudyData,
                 progress: bool = True) -> dict:
    """Train (or reload) a baseline for every seed at once and evaluate it like lazy Q."""
    name, _ = parse_method(spec)
    method_dir = _method_dir(run_dir, spec)
    method_dir.mkdir(parents=True, exist_ok=True)
    push, c = config.collect.push, config.collect.push.action_length
    timings = {}
    if name in ("random", "scripted"):
        act = baselines.random_policy(c) if name == "random" else scripted_push_policy(push)
        policies, act_of = jnp.zeros(len(sd.seeds)), lambda _: _found(act)
    else:
        cfg, budget = baseline_config(spec, config, sd)
        record = {"method": name, "budget": budget, "config": dataclasses.asdict(cfg),
                  "seeds": list(sd.seeds)}
        meta = method_dir / "config.json"
        if meta.exists() and json.loads(meta.read_text()) != record:
            raise RunDirError(f"{method_dir} holds {spec} trained with another config; "
                              "pass --overwrite or pick another --run-dir")
        steps_bar = tqdm(total=cfg.steps, unit="step", desc=f"{spec}: training (all seeds)",
                         disable=not progress, leave=False)

        def on_step(i):  # once per seed under vmap: move the bar, never back
            if int(i) > steps_bar.n:
                steps_bar.update(int(i) - steps_bar.n)

        agent = baselines.make(name, cfg, c, progress=on_step if progress else None)
        keys = jnp.stack([jax.random.fold_in(run_keys(seed_config(config, s))["train"],
                                             zlib.crc32(name.encode())) for s in sd.seeds])
        train = over_seeds(agent.train, len(sd.seeds))
        abstract = jax.eval_shape(lambda k, d, n: train(k, d, n)[0], keys, sd.stacked, sd.n_valid)
        checkpointer = ocp.StandardCheckpointer()
        state_dir = (method_dir / "state").absolute()
        if state_dir.exists():
            policies = checkpointer.restore(state_dir, abstract)
            timings = json.loads((method_dir / "timings.json").read_text())
            _log(f"{spec}: reusing its trained state ({cfg.steps} steps)")
        else:
            meta.write_text(json.dumps(record, indent=1))
            _log(f"{spec}: training {len(sd.seeds)} seeds x {cfg.steps} steps of batch {cfg.batch_size}")
            t = time.perf_counter()
            policies, metrics = jax.block_until_ready(train(keys, sd.stacked, sd.n_valid))
            seconds = time.perf_counter() - t
            checkpointer.save(state_dir, policies)
            checkpointer.wait_until_finished()
            (method_dir / "metrics.json").write_text(json.dumps(
                {k: np.asarray(v).round(5).tolist() for k, v in jax.device_get(metrics).items()}))
            timings = {"train_s": round(seconds, 1), "steps": cfg.steps,
                       "steps_per_s": round(cfg.steps * len(sd.seeds) / seconds, 1)}
            (method_dir / "timings.json").write_text(json.dumps(timings))
        steps_bar.close()
        act_of = lambda st: _found(agent.policy(st))
    eval_path = method_dir / "eval.json"
    if eval_path.exists():
        per_seed = json.loads(eval_path.read_text())
        if [r["seed"] for r in per_seed] == list(sd.seeds):
            return {"per_seed_eval": per_seed, "timings": timings}
    _log(f"{spec}: evaluating all seeds (protocols A and B)")
    t = time.perf_counter()
    per_seed, _, _ = evaluate_stacked(push, config.eval, act_of, policies, sd.seeds)
    timings["eval_s"] = round(time.perf_counter() - t, 1)
    eval_path.write_text(json.dumps(per_seed, indent=1))
    (method_dir / "timings.json").write_text(json.dumps(timings))
    return {"per_seed_eval": per_seed, "timings": timings}


# ----------------------------------------------------------------------------- results


def seed_rates(result: dict) -> dict:
    """The per-seed numbers a study reports, from one evaluation (``eval/results.json``)."""
    a, b = result["protocol_a"], result["protocol_b"]
    correct = np.array([row["correct"] for row in a["per_goal"]])
    total = np.array([row["correct"] + row["wrong"] + row["not_pushed"] for row in a["per_goal"]])
    return {"seed": result["seed"], **direction_rates(a),
            "long_horizon_successes": b["successes"], "long_horizon_rollouts": b["rollouts"],
            "long_horizon_success_rate": b["successes"] / b["rollouts"],
            "per_direction_correct_rate": (correct / total).round(6).tolist(),
            "not_pushed_rate": float(sum(r["not_pushed"] for r in a["per_goal"]) / total.sum())}


def method_summary(per_seed_eval: list[dict]) -> dict:
    """``{"per_seed": [...], "summary": {rate: {mean, ci95, sd, n}}, "per_direction": [...]}``."""
    rows = [seed_rates(r) for r in per_seed_eval]
    summary = {name: t_interval([row[name] for row in rows])
               for name in (*RATES, "not_pushed_rate")
               if all(np.isfinite(row[name]) for row in rows)}
    goals = [row["goal"] for row in per_seed_eval[0]["protocol_a"]["per_goal"]]
    per_direction = [{"goal": g, **t_interval([row["per_direction_correct_rate"][i] for row in rows])}
                     for i, g in enumerate(goals)]
    return {"per_seed": rows, "summary": summary, "per_direction": per_direction}


def dataset_table(sd: StudyData) -> dict:
    """Positive rewards per goal octant, per seed and as mean +- CI over the seeds."""
    counts = np.array([[o["positive"] for o in s["reward_by_goal_octant"]] for s in sd.summaries])
    axis, diag = counts[:, 0::2], counts[:, 1::2]
    worst = diag.max(axis=1) / np.maximum(axis.min(axis=1), 1)
    return {"positives_by_octant": {"centre_deg": [45 * i for i in range(8)],
                                    "per_seed": counts.tolist(),
                                    "mean": counts.mean(axis=0).round(1).tolist()},
            "moves_that_moved_disk": [s["moves_that_moved_disk"] for s in sd.summaries],
            "rows": [s["rows"] for s in sd.summaries],
            "diagonal_to_axis_ratio_of_means": float(diag.mean(axis=0).max() / axis.mean(axis=0).min()),
            "diagonal_to_axis_ratio_worst_per_seed": worst.round(3).tolist()}


def earlier_methods(run_dir: Path, seeds: Sequence[int], methods: Sequence[str]) -> dict:
    """The rows of ``run_dir/results.json`` for methods an earlier invocation of this
    study ran and this one does not (same seeds and study version; the config was
    checked by the caller), so that resuming with a subset of the methods adds to the
    table instead of dropping rows."""
    path = run_dir / "results.json"
    if not path.exists():
        return {}
    old = json.loads(path.read_text())
    if old.get("version") != STUDY_VERSION or old.get("seeds") != list(seeds):
        return {}
    return {name: m for name, m in old.get("methods", {}).items() if name not in methods}


def write_results(run_dir: Path, config: Config, sd: StudyData, methods: dict[str, dict],
                  earlier: dict | None = None) -> dict:
    """Write ``results.json``, ``summary.md`` and the figures for the ``methods`` run
    now (``{spec: {"per_seed_eval", "timings"}}``) after the ``earlier`` rows (as
    returned by :func:`earlier_methods`)."""
    results = {"version": STUDY_VERSION, "seeds": list(sd.seeds),
               "ci": "95 % Student-t interval over seeds (clipped to [0, 1])",
               "datasets": dataset_table(sd),
               "methods": {**(earlier or {}),
                           **{name: {**method_summary(m["per_seed_eval"]), "timings": m["timings"]}
                              for name, m in methods.items()}}}
    (run_dir / "results.json").write_text(json.dumps(results, indent=1))
    (run_dir / "summary.md").write_text(summary_markdown(results))
    from lazyq_jax import plots

    plots.study_per_direction(results, run_dir / "figures" / "per_direction.png")
    if len(results["methods"]) > 1:
        plots.study_methods(results, run_dir / "figures" / "methods.png")
    return results


def summary_markdown(results: dict) -> str:
    seeds = results["seeds"]
    lines = [f"Study over {len(seeds)} seeds ({', '.join(map(str, seeds))}); "
             f"mean [{results['ci']}].", "",
             "| method | axis correct | diagonal correct | all 16 correct | long horizon | training |",
             "|---|---|---|---|---|---|"]
    for name, m in results["methods"].items():
        s = m["summary"]
        cell = lambda key: format_ci(s[key]) if key in s else "–"
        t = m["timings"]
        train = (f"{t['train_s']:.0f} s" if t.get("train_s") else "–") + (
            f" ({t['steps_per_s']:.0f} steps/s)" if t.get("steps_per_s") else "")
        lines.append(f"| {name} | {cell('axis_correct_rate')} | {cell('diagonal_correct_rate')} | "
                     f"{cell('overall_correct_rate')} | {cell('long_horizon_success_rate')} | "
                     f"{train} |")
    d = results["datasets"]
    lines += ["", "Positive rewards per goal octant (mean over seeds): "
              + ", ".join(f"{c}°: {m:.0f}" for c, m in zip(d["positives_by_octant"]["centre_deg"],
                                                          d["positives_by_octant"]["mean"])),
              f"(largest diagonal / smallest axis octant mean: "
              f"{d['diagonal_to_axis_ratio_of_means']:.2f}).", ""]
    return "\n".join(lines)


# ----------------------------------------------------------------------------- driver


def _check_study_dir(run_dir: Path, config: Config, seeds, resume: bool, overwrite: bool) -> None:
    path = run_dir / "study.json"
    record = {"version": STUDY_VERSION, "seeds": list(seeds), "config": to_dict(config)}
    if path.exists():
        if overwrite:
            for child in run_dir.iterdir():
                shutil.rmtree(child) if child.is_dir() else child.unlink()
        elif not resume:
            raise RunDirError(f"{run_dir} already holds a study; continue it with --resume, "
                              "replace it with --overwrite, or pick another --run-dir")
        else:
            stored = json.loads(path.read_text())
            if stored.get("seeds") != list(seeds) or stored.get("config") != record["config"]:
                diff = "seeds" if stored.get("seeds") != list(seeds) else "config"
                try:
                    old = from_dict(Config, stored["config"])
                    fields = _diff(to_dict(old), to_dict(config))
                except (ConfigError, KeyError, TypeError):
                    fields = []
                raise RunDirError(f"{run_dir} holds a study with other {diff}"
                                  + (f" ({', '.join(fields)})" if fields else "")
                                  + "; pass --overwrite to replace it or pick another --run-dir")
    run_dir.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(record, indent=1))


def _diff(a, b, prefix=""):
    if isinstance(a, dict) and isinstance(b, dict):
        return [d for key in sorted(set(a) | set(b))
                for d in _diff(a.get(key), b.get(key), f"{prefix}{key}.")]
    return [] if a == b else [prefix.rstrip(".")]


def run_online(config: Config, run_dir: Path, sd: StudyData, progress: bool = True) -> dict:
    """Online lazy Q (``config.online.rounds > 0``) for every seed, one seed after another
    (each seed's data grows with its own policy, so the seeds are not vmapped); round 0
    is the seed's random dataset of the study.  Resumes per seed; writes the learning
    curve over the seeds to ``figures/online_curve.png``."""
    from lazyq_jax import plots
    from lazyq_jax.online import evaluate_online, fit_online, read_rounds

    per_seed, timings = [], {"train_s": 0.0, "eval_s": 0.0}
    for seed in sd.seeds:
        seed_dir, cfg = run_dir / "seeds" / str(seed), seed_config(config, seed)
        _log(f"online lazy: seed {seed}")
        t = time.perf_counter()
        state, data, n_valid, fns = fit_online(cfg, seed_dir, resume=True, progress=progress)
        timings["train_s"] += time.perf_counter() - t
        t = time.perf_counter()
        result = evaluate_online(cfg, seed_dir, state, data, n_valid, fns, figures=False)
        timings["eval_s"] += time.perf_counter() - t
        per_seed.append({k: result[k] for k in ("protocol_a", "protocol_b", "seed", "eval_config",
                                                "moves")})
    plots.online_curve([read_rounds(run_dir / "seeds" / str(s)) for s in sd.seeds],
                       run_dir / "figures" / "online_curve.png")
    return {"per_seed_eval": per_seed, "timings": {k: round(v, 1) for k, v in timings.items()}}


def run_method(spec: str, config: Config, run_dir: Path, sd: StudyData, progress: bool) -> dict:
    if spec == "lazy" and config.online.rounds:
        return run_online(config, run_dir, sd, progress)
    if spec == "lazy":
        return run_lazy(config, run_dir, sd, progress)
    return run_baseline(spec, config, run_dir, sd, progress)


def run_study(config: Config, run_dir: str | Path, *, seeds: Sequence[int],
              methods: Sequence[str] = ("lazy",), resume: bool = False, overwrite: bool = False,
              progress: bool = True) -> dict:
    """Run (or resume) a study: every method on every seed's data; write the results.

    ``resume``: continue a study in ``run_dir`` with the same config and seeds
    (refused otherwise); the methods of earlier runs of it that are not named again
    keep their rows in ``results.json``.  ``overwrite``: delete it first.  Returns the
    contents of ``results.json``.
    """
    seeds, methods = check_seeds(seeds), check_methods(methods)
    learned = [m for m in methods if parse_method(m)[0] not in ("lazy", "random", "scripted")]
    if config.online.rounds and learned:
        raise ConfigError(f"an online study (online.rounds > 0) runs lazy, random and scripted; "
                          f"{learned} would train on round 0's random data only: run them in an "
                          "offline study")
    run_dir = Path(run_dir)
    _check_study_dir(run_dir, config, seeds, resume, overwrite)
    t = time.perf_counter()
    _log(f"study: {len(seeds)} seeds {list(seeds)}, methods {list(methods)} -> {run_dir}")
    sd = prepare_study_data(config, run_dir, seeds, progress)
    (run_dir / "timings.json").write_text(json.dumps({"datasets_s": round(time.perf_counter() - t, 1)}))
    _log(f"study: datasets ready ({time.perf_counter() - t:.1f} s; rows "
         f"{min(d.size for d in sd.datasets):,}-{sd.capacity:,})")
    earlier = earlier_methods(run_dir, seeds, methods) if resume else {}
    records = {spec: run_method(spec, config, run_dir, sd, progress) for spec in methods}
    if earlier:
        _log(f"study: results.json keeps {', '.join(earlier)} from an earlier run of this "
             "study (--overwrite starts afresh)")
    results = write_results(run_dir, config, sd, records, earlier)
    _log(summary_markdown(results))
    _log(f"study: done in {time.perf_counter() - t:.1f} s -> {run_dir / 'results.json'}")
    return results
