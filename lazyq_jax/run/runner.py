"""One runner for every task, agent and data source: ``run(config, run_dir, seeds, methods)``.

For every method (an agent of :mod:`lazyq_jax.agents`, or a task's scripted
controller) on every seed's data (static, or grown by online rounds):

1. **train**: ``agent.blocks`` blocks (lazy Q: its cycles), each one program over all
   seeds (``jax.vmap`` of ``agent.run_block``; one seed runs unbatched), a checkpoint
   of the seeds' stacked states after every block; ``resume`` continues from the newest
   intact one.  Between blocks the host runs ``agent.prepare`` (lazy Q's neighbour
   search) and, online, the rounds (the task's rollouts of the current policies).
2. **evaluate**: the task's protocols for all seeds in one program; ``eval.json``,
   figures and an animation of seed 0's rollouts.
3. **results**: per seed and mean with 95 % CI (``results.json``, ``summary.md``).

A single run (``train``) is a run of one seed.  :func:`evaluate_run` re-evaluates a
finished run from its checkpoints, :func:`load_policy` hands user code the trained
policy of any run.  Layout and guard: :mod:`lazyq_jax.run.rundir`.
"""

from __future__ import annotations

import dataclasses
import json
import time
import zlib
from pathlib import Path
from typing import Any, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh
from tqdm.auto import tqdm

from lazyq_jax import agents, tasks
from lazyq_jax.agents import Agent, FixedPolicy, LazyConfig, Problem, Spec
from lazyq_jax.agents.base import stack_trees
from lazyq_jax.checkpoint import CheckpointError, checkpoint_writer, latest_step, load_latest_intact
from lazyq_jax.config import (POLICY_FIELDS, Config, ConfigError, NeighbourConfig, override,
                              policy_settings, to_dict)
from lazyq_jax.data import DatasetError
from lazyq_jax.keys import purpose_key
from lazyq_jax.parallel import is_main_process, make_mesh, over_seeds, put, replicated
from lazyq_jax.plots import online_curve
from lazyq_jax.run.results import earlier_methods, method_label, write_results
from lazyq_jax.run.rundir import (MethodSpec, RunDirError, append_jsonl, as_json, check_methods,
                                  check_seeds, field_defaults, keep_jsonl, locked, open_method, open_run, parse_method,
                                  read_jsonl, write_json)
from lazyq_jax.run.sources import OnlineRounds, SeedData, log, static_data
from lazyq_jax.tasks import Task
from lazyq_jax.train import check_mesh


@dataclasses.dataclass
class Context:
    """One run: its task, config, directory, seeds, devices and progress display."""

    task: Task
    config: Config
    run_dir: Path
    seeds: tuple[int, ...]
    mesh: Mesh | None
    progress: bool
    #: the lazy policy's settings changed from the run's own (``evaluate --set``), by name
    acting: dict = dataclasses.field(default_factory=dict)

    @property
    def online(self) -> OnlineRounds | None:
        return OnlineRounds(self.task, self.config, self.run_dir) if self.config.online.rounds else None


# ----------------------------------------------------------------------------- agents


def lazy_steps(config: Config, sd: SeedData) -> int:
    """Lazy Q's gradient steps on the smallest of the seeds' datasets: the budget unit."""
    tc = config.train
    return tc.cycles * tc.epochs * (int(np.min(sd.n_valid)) // tc.batch_size)


def _record_defaults(record: dict) -> dict:
    """The defaults of a method record's sections (see :func:`open_method`)."""
    return {"neighbours": field_defaults(NeighbourConfig())} if record.get("method") == "lazy" else {}


def build_agent(ctx: Context, spec: MethodSpec, sd: SeedData) -> tuple[Agent, dict]:
    """The agent of ``spec`` for this run, and the record of its settings (``method.json``).

    Baselines get lazy Q's budget (its gradient steps times ``budget``), batch size,
    network width and depth and discount, then the task's settings for the method
    (:meth:`~lazyq_jax.tasks.base.Task.method_defaults`, e.g. a benchmark's published
    ones), then the spec's own overrides."""
    task, config = ctx.task, ctx.config
    problem = task.problem(config)
    if spec.name == "lazy":
        mesh = ctx.mesh if len(ctx.seeds) == 1 else None
        agent = agents.make("lazy", LazyConfig(train=config.train, neighbours=config.neighbours),
                            problem=problem, mesh=mesh)
        train = {k: v for k, v in dataclasses.asdict(config.train).items() if k != "cycles"}
        return agent, {"method": "lazy", "train": train, "neighbours": to_dict(config.neighbours),
                       "online": to_dict(config.online)}
    if spec.name == "scripted":
        act = task.scripted(config)
        if act is None:
            raise ConfigError(f"task {task.name!r} has no scripted controller; drop 'scripted'")
        return FixedPolicy("scripted", act, problem), {"method": "scripted"}
    if spec.name == "random":
        return agents.make("random", problem=problem), {"method": "random"}
    fields = dict(spec.options)
    try:
        budget = float(fields.pop("budget", 1.0))
    except ValueError:
        raise ConfigError(f"{spec.text!r}: budget must be a number") from None
    if not budget > 0:
        raise ConfigError(f"{spec.text!r}: budget must be > 0")
    tc = config.train
    cfg = agents.config_class(spec.name)(
        steps=max(1, round(budget * lazy_steps(config, sd))), batch_size=tc.batch_size,
        width=tc.width, depth=tc.depth, gamma=tc.gamma)
    cfg = dataclasses.replace(cfg, **task.method_defaults(spec.name))
    cfg = override(cfg, [f"{k}={v}" for k, v in fields.items()])
    return (agents.make(spec.name, cfg, problem=problem),
            {"method": spec.name, "config": dataclasses.asdict(cfg), "budget": budget})


def train_key(seed: int, name: str) -> jax.Array:
    """A seed's training key for method ``name`` (lazy Q: the seed's ``train`` stream; the
    others fold in a hash of their name, so methods draw independent streams)."""
    key = purpose_key(seed, "train")
    return key if name == "lazy" else jax.random.fold_in(key, zlib.crc32(name.encode()))


# ----------------------------------------------------------------------------- training


def _metrics_record(block: int, seconds: float, metrics: dict) -> dict:
    return {"block": block, "seconds": round(seconds, 2),
            **{k: np.asarray(v).round(5).tolist() for k, v in metrics.items()}}


def _log_block(spec: MethodSpec, block: int, total: int, record: dict) -> None:
    shown = [k for k in ("loss", "clip_fraction", "neighbour_level0_fraction", "critic_loss",
                         "value_loss", "actor_loss", "td_loss") if k in record][:3]
    parts = [f"{k} {np.mean(record[k]):.4g}" for k in shown]
    log(f"{spec.text}: block {block}/{total}: " + "  ".join(parts) + f"  ({record['seconds']:.1f} s)")


def _seed_slice(tree, i: int):
    return jax.tree.map(lambda x: x[i], tree)


def restore(ctx: Context, agent: Agent, spec: MethodSpec, method_dir: Path, abstract) -> tuple[Any, int] | None:
    """The newest intact checkpoint of this method (its seeds), or None."""
    ckpt = method_dir / "checkpoints"
    if latest_step(ckpt) is None:
        return None

    def check(path, meta):
        if meta.get("seeds") != list(ctx.seeds) or meta.get("method") != spec.text:
            raise CheckpointError(f"{path} holds {meta.get('method')} of seeds {meta.get('seeds')}, "
                                  f"not {spec.text} of seeds {list(ctx.seeds)}")

    sharding = replicated(ctx.mesh) if getattr(agent, "mesh", None) is not None else None
    found = load_latest_intact(ckpt, abstract, sharding, check=check, warn=log)
    return None if found is None else (found[0], int(found[1]["step"]))


def train_method(ctx: Context, agent: Agent, spec: MethodSpec, method_dir: Path, sd: SeedData
                 ) -> tuple[Any, SeedData, dict]:
    """Train (or resume) ``agent`` on every seed; returns the stacked states, the data they
    were trained on (grown by the online rounds) and the seconds spent."""
    n_seeds, online = len(ctx.seeds), ctx.online if spec.name == "lazy" else None
    keys = jnp.stack([train_key(s, agent.name) for s in ctx.seeds])
    init = over_seeds(agent.init, n_seeds)
    timings = {"prepare_s": 0.0, "train_s": 0.0}
    if agent.blocks == 0:  # nothing to learn
        return init(keys, sd.stacked), sd, timings
    total = online.total_blocks() if online else agent.blocks
    abstract = jax.eval_shape(init, keys, sd.stacked)
    found = restore(ctx, agent, spec, method_dir, abstract)
    metrics_path = method_dir / "metrics.jsonl"
    if found is None:
        states, first = init(keys, sd.stacked), 0
        if is_main_process():
            metrics_path.write_text("")
    else:
        states, first = found
        keep_jsonl(metrics_path, lambda r: r["block"] <= first)
        log(f"{spec.text}: resuming after block {first} of {total}")
    round0 = sd.n_valid.copy()
    if online is not None:
        sd = online.load(sd, online.rounds_with_data(first))
        keep_jsonl(method_dir / "rounds.jsonl", lambda r: r["block"] <= first)
    mesh = getattr(agent, "mesh", None)
    place = (lambda x: x) if mesh is None else (lambda x: put(x, replicated(mesh)))
    states, stacked = place(states), place(sd.stacked)
    run_block = over_seeds(agent.run_block, n_seeds)
    meta = {"method": spec.text, "seeds": list(ctx.seeds), "task": ctx.task.name}
    bar = tqdm(total=total, initial=first, desc=f"{spec.text}: training ({n_seeds} seed"
               f"{'s' if n_seeds > 1 else ''})", unit="block", disable=not ctx.progress, leave=False)
    aux, round_timing = None, {}
    if online is not None and first > 0:
        _round_end(ctx, agent, online, states, sd, method_dir, first, {}, run_block)
    with checkpoint_writer(method_dir / "checkpoints") as save:
        for block in range(first, total):
            r = online.round_starting(block) if online is not None else None
            if r is not None:
                t = time.perf_counter()
                policies = agent.policies(states, sd.stacked, sd.n_valid)
                sd, counts = online.collect(_explorer(ctx, agent), policies, sd, r, round0)
                round_timing = {"collect_s": round(time.perf_counter() - t, 2), "counts": counts}
                stacked, aux = place(sd.stacked), None  # the data grew: new neighbourhoods
            if aux is None or agent.refresh(block):
                t = time.perf_counter()
                aux = stack_trees([agent.prepare(s, _seed_slice(sd.stacked, i), int(sd.n_valid[i]),
                                                 block) for i, s in enumerate(ctx.seeds)])
                timings["prepare_s"] += time.perf_counter() - t
            t = time.perf_counter()
            states, metrics = run_block(states, stacked, aux, jnp.asarray(sd.n_valid))
            metrics = jax.device_get(metrics)
            seconds = time.perf_counter() - t
            timings["train_s"] += seconds
            save(states, block + 1, meta)
            record = _metrics_record(block + 1, seconds, metrics)
            append_jsonl(metrics_path, record)
            bar.update(1)
            _log_block(spec, block + 1, total, record)
            if online is not None:
                if _round_end(ctx, agent, online, states, sd, method_dir, block + 1, round_timing, run_block):
                    round_timing = {}
    bar.close()
    return states, sd, timings


def _compiled(fn) -> int | None:
    """How many programs a jitted function (or :func:`over_seeds`' one-seed wrapper) holds."""
    fn = getattr(fn, "jitted", fn)
    return fn._cache_size() if hasattr(fn, "_cache_size") else None


_EXPLORERS: dict = {}


def _explorer(ctx: Context, agent: Agent):
    """The task's online round over the stacked policies (compiled once per data shape)."""
    key = (id(agent), ctx.task.name, ctx.config, len(ctx.seeds))
    if key not in _EXPLORERS:
        _EXPLORERS.clear()
        task, config = ctx.task, ctx.config
        _EXPLORERS[key] = over_seeds(lambda p, k: task.explore(agent.act(p), k, config), len(ctx.seeds))
    return _EXPLORERS[key]


def _round_end(ctx: Context, agent: Agent, online: OnlineRounds, states, sd: SeedData,
               method_dir: Path, block: int, timing: dict, run_block) -> bool:
    """After the last block of a round: the task's quick evaluation of every seed, recorded
    with the round's data in ``rounds.jsonl`` (once per round), and how often the round's
    programs compiled so far (once per shape of the padded data: see :meth:`OnlineRounds.size_for`)."""
    path = method_dir / "rounds.jsonl"
    ends = {online.round_end(r): r for r in range(ctx.config.online.rounds + 1)}
    if block not in ends or any(rec["round"] == ends[block] for rec in read_jsonl(path)):
        return False
    r = ends[block]
    t = time.perf_counter()
    policies = agent.policies(states, sd.stacked, sd.n_valid)
    ev = ctx.task.evaluate(agent.act, policies, ctx.config, ctx.seeds, quick=True)
    per_move = online.per_move
    seeds = []
    for i, seed in enumerate(ctx.seeds):
        rates = ctx.task.seed_rates(ev.per_seed[i])
        seeds.append({"seed": seed, "moves_total": int(sd.n_valid[i]) // per_move,
                      "protocol_a": {k: v for k, v in rates.items() if isinstance(v, float)}})
    timing = dict(timing)
    counts = timing.pop("counts", {})
    timing["eval_s"] = round(time.perf_counter() - t, 2)
    compiled = {"run_block": _compiled(run_block), "explore": _compiled(_explorer(ctx, agent))}
    record = {"round": r, "block": block, "seeds": seeds, "counts": counts, "seconds": timing,
              "compiled": compiled}
    append_jsonl(path, record)
    rates = [s["protocol_a"].get("overall_correct_rate", np.nan) for s in seeds]
    log(f"round {r}/{ctx.config.online.rounds}: moves {[s['moves_total'] for s in seeds]}; quick "
        f"protocol A, all goals correct {np.round(rates, 3).tolist()}")
    return True


# ----------------------------------------------------------------------------- evaluation


def eval_stamp(config: Config, block: int, seeds: Sequence[int], acting: dict | None = None) -> dict:
    """What an ``eval.json`` was made from, as JSON gives it back (tuples as lists), so that a
    stored evaluation compares equal to the stamp of the same settings and is reused;
    ``acting``: the policy settings changed from the run's own (:data:`POLICY_FIELDS`), if any."""
    stamp = {"eval": to_dict(config.eval), "block": int(block), "seeds": [int(s) for s in seeds]}
    return as_json({**stamp, "acting": acting} if acting else stamp)


def stored_evaluation(path: Path, stamp: dict) -> list[dict] | None:
    """The per-seed results in ``eval.json`` at ``path`` if it was made with ``stamp``
    (:func:`eval_stamp`), else ``None``."""
    if not path.exists():
        return None
    stored = json.loads(path.read_text())
    keys = {*stamp, "acting"}  # an evaluation with other policy settings is never reused
    return stored["per_seed"] if all(stored.get(k) == stamp.get(k) for k in keys) else None


def evaluate_method(ctx: Context, agent: Agent, spec: MethodSpec, method_dir: Path, states,
                    sd: SeedData, *, block: int, force: bool = False, figures: bool = True) -> list[dict]:
    """The task's evaluation of every seed (``eval.json``), reused when it was made with the
    same evaluation settings from the same checkpoint; figures and an animation of seed 0."""
    path = method_dir / "eval.json"
    stamp = eval_stamp(ctx.config, block, ctx.seeds, method_acting(ctx, spec))
    stored = None if force else stored_evaluation(path, stamp)
    if stored is not None:
        return stored
    t = time.perf_counter()
    policies = agent.policies(states, sd.stacked, sd.n_valid)
    ev = ctx.task.evaluate(agent.act, policies, ctx.config, ctx.seeds)
    seconds = time.perf_counter() - t
    write_json(path, {**stamp, "seconds": round(seconds, 1), "per_seed": ev.per_seed})
    label = method_label(spec.text, stamp.get("acting"))
    for result in ev.per_seed:
        log(f"{label}: seed {result['seed']}: {ctx.task.log_line(result)}")
    if figures and is_main_process():
        out = ctx.run_dir / "figures" / spec.dirname  # the figures show the latest evaluation
        rollouts = _seed_slice(ev.rollouts, 0)
        value_fn = agent.value_fn(_seed_slice(states, 0)) if hasattr(agent, "value_fn") else None
        ctx.task.figures(out, ev.per_seed[0], rollouts, ctx.config, value_fn)
        ctx.task.animate(out / "rollouts.gif", rollouts, ctx.config)
        rounds = read_jsonl(method_dir / "rounds.jsonl")
        if rounds:
            online_curve([[{**rec["seeds"][i], "moves_total": rec["seeds"][i]["moves_total"]}
                           for rec in rounds] for i in range(len(ctx.seeds))],
                         out / "online_curve.png")
    return ev.per_seed


# ----------------------------------------------------------------------------- the runs


def _context(config: Config, run_dir, seeds, progress: bool) -> Context:
    task = tasks.get(config.task)
    task.check(config)
    mesh = make_mesh(config.parallel)
    check_mesh(config.train, mesh)  # before anything is collected
    return Context(task, config, Path(run_dir), check_seeds(seeds), mesh, progress)


def _data(ctx: Context) -> SeedData:
    """The seeds' static data (online: checked against the budget, padded to its capacity)."""
    sd = static_data(ctx.task, ctx.config, ctx.run_dir, ctx.seeds, mesh=ctx.mesh,
                     progress=ctx.progress)
    return sd if ctx.online is None else ctx.online.padded(sd)


def run(config: Config, run_dir: str | Path, *, seeds: Sequence[int] | None = None,
        methods: Sequence[str] = ("lazy",), resume: bool = False, overwrite: bool = False,
        progress: bool = True, evaluate: bool = True) -> dict:
    """Run (or resume) ``methods`` on ``seeds`` (default ``[config.seed]``) of ``config``'s task:
    data, training with a checkpoint per block, evaluation, results (module docstring).

    ``resume``: continue the run in ``run_dir`` (same task, seeds and config, up to the
    evaluation settings and more cycles; methods named anew are added, the rows of
    methods not named again are kept).  ``overwrite``: delete it first.  Refused
    combinations, and a directory another process holds (:func:`~lazyq_jax.run.rundir.locked`),
    fail before anything in ``run_dir`` is touched.  Returns the contents
    of ``results.json`` (``{}`` without ``evaluate``).
    """
    seeds = [config.seed] if seeds is None else seeds
    ctx = _context(config, run_dir, seeds, progress)
    specs = check_methods(methods)
    learned = [s.text for s in specs if s.name not in ("lazy", "random", "scripted")]
    if config.online.rounds and learned:
        raise ConfigError(f"an online run (online.rounds > 0) grows its data with lazy Q's policy; "
                          f"{learned} would train on round 0's random data only: run them offline")
    with locked(ctx.run_dir):  # before the directory is touched or anything compiles
        open_run(ctx.run_dir, config, ctx.seeds, resume=resume, overwrite=overwrite)
        t0 = time.perf_counter()
        log(f"run: task {ctx.task.name}, seeds {list(ctx.seeds)}, methods {[s.text for s in specs]} -> "
            f"{ctx.run_dir} ({ctx.mesh.size} {ctx.mesh.devices.flat[0].platform} device"
            f"{'s' if ctx.mesh.size > 1 else ''})")
        sd = _data(ctx)
        write_json(ctx.run_dir / "timings.json", {"data_s": round(time.perf_counter() - t0, 1)})
        spec_of_data = Spec.of(_seed_slice(sd.stacked, 0))
        for spec in specs:  # every method can learn from these data, before any trains
            build_agent(ctx, spec, sd)[0].check_data(spec_of_data)
        records = {}
        for spec in specs:
            records[spec.text] = _run_method(ctx, spec, sd, evaluate=evaluate)
        if not evaluate or not is_main_process():
            return {}
        earlier = earlier_methods(ctx.run_dir, ctx.seeds) if resume else {}
        results = write_results(ctx.task, ctx.run_dir, ctx.seeds, sd.summaries, records, earlier)
        log((ctx.run_dir / "summary.md").read_text())
        log(f"run: done in {time.perf_counter() - t0:.1f} s -> {ctx.run_dir / 'results.json'}")
        return results


def _run_method(ctx: Context, spec: MethodSpec, sd: SeedData, *, evaluate: bool,
                force_eval: bool = False, figures: bool = True, train: bool = True) -> dict:
    method_dir = ctx.run_dir / spec.dirname
    agent, record = build_agent(ctx, spec, sd)
    timing_path = method_dir / "timings.json"
    record["spec"] = spec.text
    if train:
        open_method(method_dir, record, _record_defaults(record))
        states, sd, spent = train_method(ctx, agent, spec, method_dir, sd)
    else:
        states, sd, spent = load_states(ctx, agent, spec, method_dir, sd), sd, {}
        if ctx.online is not None and spec.name == "lazy":
            sd = ctx.online.load(sd, ctx.online.rounds_with_data(ctx.online.total_blocks()))
    timings = json.loads(timing_path.read_text()) if timing_path.exists() else {}
    for name, seconds in spent.items():  # accumulated over resumed sessions
        timings[name] = round(timings.get(name, 0.0) + seconds, 1)
    steps = getattr(agent.config, "steps", None)
    if spec.name == "lazy":
        steps = lazy_steps(ctx.config, sd)
    if steps and timings.get("train_s"):
        timings["steps"] = steps
        timings["steps_per_s"] = round(steps * len(ctx.seeds) / timings["train_s"], 1)
    write_json(timing_path, timings)
    if not evaluate or not is_main_process():
        return {"timings": timings}
    acting = method_acting(ctx, spec)
    blocks = ctx.online.total_blocks() if ctx.online is not None and spec.name == "lazy" else agent.blocks
    t = time.perf_counter()
    per_seed = evaluate_method(ctx, agent, spec, method_dir, states, sd, block=blocks,
                               force=force_eval, figures=figures)
    if time.perf_counter() - t > 1:
        timings["eval_s"] = round(time.perf_counter() - t, 1)
        write_json(timing_path, timings)
    return {"per_seed_eval": per_seed, "timings": timings, **({"acting": acting} if acting else {})}


def load_states(ctx: Context, agent: Agent, spec: MethodSpec, method_dir: Path, sd: SeedData):
    """A finished method's trained states (stacked over the run's seeds)."""
    keys = jnp.stack([train_key(s, agent.name) for s in ctx.seeds])
    init = over_seeds(agent.init, len(ctx.seeds))
    if agent.blocks == 0:
        return init(keys, sd.stacked)
    abstract = jax.eval_shape(init, keys, sd.stacked)
    found = restore(ctx, agent, spec, method_dir, abstract)
    total = ctx.online.total_blocks() if ctx.online is not None and spec.name == "lazy" else agent.blocks
    if found is None or found[1] < total:
        done = 0 if found is None else found[1]
        raise RunDirError(f"{method_dir}: {spec.text} is not trained ({done} of {total} blocks); "
                          "finish it with `train`/`study` --resume")
    return found[0]


def open_existing(run_dir: str | Path, overrides: Sequence[str] = ()) -> tuple[Config, list[int]]:
    """The config (with ``eval.*`` and :data:`POLICY_FIELDS` overrides) and seeds of the run
    in ``run_dir``."""
    path = Path(run_dir) / "run.json"
    if not path.exists():
        old = (Path(run_dir) / "checkpoints").exists() or (Path(run_dir) / "study.json").exists()
        raise RunDirError(f"{run_dir}: " + ("a run of an older lazyq-jax; train it again"
                                            if old else "no run here (no run.json); train first"))
    stored = json.loads(path.read_text())
    allowed = lambda a: a.strip().startswith("eval.") or a.split("=")[0].strip() in POLICY_FIELDS
    bad = [a for a in overrides if not allowed(a)]
    if bad:
        raise ConfigError(f"only eval.* settings and the lazy policy's {', '.join(POLICY_FIELDS)} can "
                          f"change for a trained run, got {bad}; train anew (--run-dir elsewhere) to "
                          "change anything else")
    config = override(tasks.config_from_dict(stored["config"]), list(overrides))
    return config, stored["seeds"]


def policy_changes(trained: Config, config: Config) -> dict:
    """The :data:`POLICY_FIELDS` in which ``config`` differs from the run's ``trained`` one."""
    before = policy_settings(trained)
    return {f: v for f, v in policy_settings(config).items() if v != before[f]}


def method_acting(ctx: Context, spec: MethodSpec) -> dict:
    """The policy settings a method is evaluated with that differ from its run's (lazy Q's
    policy only: the other agents act by their own networks)."""
    return ctx.acting if spec.name == "lazy" else {}


def _open_trained(run_dir: str | Path, overrides: Sequence[str], progress: bool) -> Context:
    """The context of a trained run with ``overrides`` (:func:`open_existing`) applied."""
    config, seeds = open_existing(run_dir, overrides)
    ctx = _context(config, run_dir, seeds, progress)
    ctx.acting = policy_changes(open_existing(run_dir)[0], config)
    return ctx


def trained_methods(run_dir: Path) -> list[str]:
    """The methods of a run directory, in the order they were first trained."""
    paths = sorted(run_dir.glob("*/method.json"), key=lambda p: p.stat().st_mtime)
    return [json.loads(path.read_text())["spec"] for path in paths]


def evaluate_run(run_dir: str | Path, *, methods: Sequence[str] | None = None,
                 overrides: Sequence[str] = (), figures: bool = True, progress: bool = True) -> dict:
    """Re-evaluate a trained run from its checkpoints and data (nothing is retrained):
    every method (or ``methods``), with the run's evaluation settings changed by the
    ``eval.*`` ``overrides`` and lazy Q's policy by :data:`POLICY_FIELDS` ones (e.g.
    ``neighbours.subgoal_steps=0``: the one-level step of a two-level run; the results then
    name the settings, ``"acting"``); writes ``eval.json``, ``results.json`` and the figures."""
    ctx = _open_trained(run_dir, overrides, progress)
    with locked(ctx.run_dir):
        names = list(methods) if methods else trained_methods(ctx.run_dir)
        if not names:
            raise RunDirError(f"{run_dir}: no trained method found")
        specs = check_methods(names)
        if ctx.acting and not any(spec.name == "lazy" for spec in specs):
            raise ConfigError(f"{', '.join(ctx.acting)} change lazy Q's policy; "
                              f"{run_dir} evaluates {', '.join(names)} (add lazy to --methods)")
        for spec in specs:
            if not (ctx.run_dir / spec.dirname / "method.json").exists():
                raise RunDirError(f"{run_dir}: no trained {spec.text} here; its methods: "
                                  f"{', '.join(trained_methods(ctx.run_dir))}")
        try:
            sd = _data(ctx)
        except DatasetError as e:
            raise RunDirError(f"{run_dir}: cannot evaluate: {e}") from e
        records = {spec.text: _run_method(ctx, spec, sd, evaluate=True, force_eval=True, figures=figures,
                                          train=False) for spec in specs}
        earlier = earlier_methods(ctx.run_dir, ctx.seeds)
        results = write_results(ctx.task, ctx.run_dir, ctx.seeds, sd.summaries, records, earlier)
        log((ctx.run_dir / "summary.md").read_text())
        return results


@dataclasses.dataclass
class LoadedRun:
    """A trained method of a run directory (:func:`load_run`): its ``config`` and ``task``,
    the ``agent``, the trained ``states`` stacked over ``seeds`` and the seeds' ``data``."""

    config: Config
    task: Task
    seeds: tuple[int, ...]
    agent: Agent
    states: Any
    data: SeedData

    def state(self, seed: int | None = None):
        """One seed's trained state (default: the first seed's)."""
        return _seed_slice(self.states, self.seeds.index(self.seeds[0] if seed is None else seed))

    def policy(self, seed: int | None = None):
        """``act(key, s, g) -> actions`` of one seed (jitted)."""
        i = self.seeds.index(self.seeds[0] if seed is None else seed)
        one = lambda tree: jax.tree.map(lambda x: x[i:i + 1], tree)
        policy = self.agent.policies(one(self.states), one(self.data.stacked), self.data.n_valid[i:i + 1])
        return jax.jit(self.agent.act(_seed_slice(policy, 0)))


def load_run(run_dir: str | Path, method: str = "lazy", overrides: Sequence[str] = ()) -> LoadedRun:
    """Reload a trained method of any run directory (its newest checkpoint, which must be
    finished), with the data it was trained on; nothing is retrained.  ``overrides``:
    ``eval.*`` and lazy Q's :data:`POLICY_FIELDS` settings, as for :func:`evaluate_run`."""
    ctx = _open_trained(run_dir, overrides, progress=False)
    config = ctx.config
    spec = parse_method(method)
    method_dir = ctx.run_dir / spec.dirname
    if not (method_dir / "method.json").exists():
        raise RunDirError(f"{run_dir}: no trained {method} here; its methods: "
                          f"{', '.join(trained_methods(ctx.run_dir)) or 'none'}")
    sd = _data(ctx)
    agent, _ = build_agent(ctx, spec, sd)
    if ctx.online is not None and spec.name == "lazy":
        sd = ctx.online.load(sd, ctx.online.rounds_with_data(ctx.online.total_blocks()))
    return LoadedRun(config, ctx.task, ctx.seeds, agent, load_states(ctx, agent, spec, method_dir, sd), sd)


def load_policy(run_dir: str | Path, method: str = "lazy", seed: int | None = None,
                overrides: Sequence[str] = ()):
    """The trained policy of ``method`` for ``seed`` (default: the run's first) in any run
    directory: ``act(key, s[B, d_s], g) -> actions [B, n_a]``, jitted, for user code;
    ``overrides`` as for :func:`load_run` (e.g. ``["neighbours.subgoal_steps=0"]``).

    >>> act = lazyq_jax.load_policy("runs/paper")
    >>> actions = act(jax.random.PRNGKey(0), s, g)
    """
    loaded = load_run(run_dir, method, overrides)
    if seed is not None and seed not in loaded.seeds:
        raise RunDirError(f"{run_dir} holds seeds {list(loaded.seeds)}, not {seed}")
    return loaded.policy(seed)


__all__ = ["Context", "LoadedRun", "Problem", "RunDirError", "build_agent", "evaluate_run",
           "load_policy", "load_run", "run"]
