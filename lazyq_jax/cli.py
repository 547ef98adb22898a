"""``python -m lazyq_jax collect|train|study|evaluate|plot|report|config`` (or ``lazyq ...``):
parse, then call the runner (``report``: :mod:`lazyq_jax.run.report`).

Every command takes ``--task`` (``push``, ``arm``, ``arm-long``) and ``--preset`` (the
task's named configs, ``paper`` by default), and any config field can be overridden:
``--set train.width=128 --set seed=3``.  Compiled programs are cached on disk
(``LAZYQ_COMPILE_CACHE``, see :func:`lazyq_jax.parallel.enable_compilation_cache`), so a
second run compiles little.  Devices: ``--set parallel.devices=N`` (default all),
``LAZYQ_HOST_DEVICES=N`` for N CPU devices, ``--set parallel.distributed=true`` or
``LAZYQ_DISTRIBUTED=1`` on a cluster.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from lazyq_jax import tasks
from lazyq_jax.agents import METHODS
from lazyq_jax.checkpoint import CheckpointError
from lazyq_jax.config import POLICY_FIELDS, Config, ConfigError, override, to_dict
from lazyq_jax.data import DatasetError
from lazyq_jax.parallel import (enable_compilation_cache, force_host_devices, is_main_process,
                                make_mesh, maybe_initialize_distributed)
from lazyq_jax.run import RunDirError, evaluate_run, locked, report, run
from lazyq_jax.run.benchmark import benchmark
from lazyq_jax.run.sources import static_data


LOCK_HELP = ("one process at a time: a directory another live process is writing is refused at once, "
             "naming it (pid, host, start, command); a killed process's lock is taken over")


def _config(args) -> Config:
    sets = args.set or []
    if any(a.split("=", 1)[0].strip() == "task" for a in sets):
        raise ConfigError("choose the task with --task, not --set task=...")
    config = override(tasks.preset(args.task, args.preset), sets)
    tasks.get(config.task).check(config)
    maybe_initialize_distributed(config.parallel)  # before anything touches a device
    return config


def _default_dir(args, study: bool) -> Path:
    name = args.preset if args.task == "push" else (
        args.task if args.preset == "paper" else f"{args.task}_{args.preset}")
    return Path("runs") / (f"study_{name}" if study else name)


def _methods(text: str) -> list[str]:
    return [m.strip() for m in text.split(",") if m.strip()]


def _add_common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--task", default="push", help=f"one of {', '.join(tasks.TASKS)} (default push)")
    p.add_argument("--preset", default="paper", help="one of the task's presets (default paper; "
                   "all tasks have smoke, push and the arms online)")
    p.add_argument("--run-dir", type=Path, default=None, help="output directory (default runs/<preset>, "
                   f"runs/<task>, or runs/study_...); {LOCK_HELP}")
    p.add_argument("--set", action="append", metavar="FIELD=VALUE",
                   help="override a config field, e.g. train.width=128 (repeatable)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")


def _add_resume(p: argparse.ArgumentParser) -> None:
    p.add_argument("--resume", action="store_true",
                   help="continue the run in --run-dir from its newest intact checkpoints")
    p.add_argument("--overwrite", action="store_true", help="delete the run in --run-dir first")


def cmd_collect(args) -> None:
    config = _config(args)
    run_dir = args.run_dir or _default_dir(args, study=False)
    seeds = list(range(args.first_seed, args.first_seed + args.seeds)) if args.seeds else [config.seed]
    with locked(run_dir):
        sd = static_data(tasks.get(config.task), config, run_dir, seeds, mesh=make_mesh(config.parallel),
                         progress=not args.no_progress)
    if is_main_process():
        print(json.dumps(sd.summaries[0] if len(seeds) == 1 else sd.summaries, indent=1))


def cmd_train(args) -> None:
    config = _config(args)
    run_dir = args.run_dir or _default_dir(args, study=False)
    t = time.perf_counter()
    run(config, run_dir, seeds=[config.seed], methods=_methods(args.methods), resume=args.resume,
        overwrite=args.overwrite, progress=not args.no_progress, evaluate=not args.no_eval)
    print(f"done in {time.perf_counter() - t:.1f} s; run directory: {run_dir}")


def cmd_study(args) -> None:
    config = _config(args)
    run_dir = args.run_dir or _default_dir(args, study=True)
    if args.seeds < 1:
        raise ConfigError(f"--seeds must be >= 1, got {args.seeds}")
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    run(config, run_dir, seeds=seeds, methods=_methods(args.methods), resume=args.resume,
        overwrite=args.overwrite, progress=not args.no_progress)


def cmd_benchmark(args) -> None:
    if args.seeds < 1:
        raise ConfigError(f"--seeds must be >= 1, got {args.seeds}")
    sets = args.set or []
    if any(a.split("=", 1)[0].strip() == "task" for a in sets):
        raise ConfigError("a benchmark runs its suite's tasks; choose them with --datasets, not --set task=...")
    run_dir = args.run_dir or Path("runs") / f"bench_{args.suite}"
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    command = " ".join(["python -m lazyq_jax", *sys.argv[1:]]) if sys.argv[1:2] == ["benchmark"] else ""
    datasets = None if args.datasets is None else _methods(args.datasets)
    if datasets == []:
        raise ConfigError(f"--datasets {args.datasets!r} names no dataset; leave it out for every dataset "
                          f"of {args.suite}")
    data = benchmark(args.suite, run_dir, seeds, _methods(args.methods), datasets=datasets, preset=args.preset,
                     sets=sets, progress=not args.no_progress, command=command)
    if is_main_process():
        print(f"{len(data['datasets'])} datasets -> {run_dir / 'results.json'}, {run_dir / 'results.md'}")


def cmd_evaluate(args) -> None:
    evaluate_run(args.run_dir, methods=_methods(args.methods) if args.methods else None,
                 overrides=args.set or [], figures=not args.no_figures,
                 progress=not args.no_progress)
    print(f"results: {args.run_dir / 'results.json'}" + ("" if args.no_figures else
                                                          f"; figures: {args.run_dir / 'figures'}"))


def cmd_report(args) -> int:
    if args.check or args.update:
        if args.run_dirs:
            raise RunDirError("--check and --update read the run directories from the blocks; name no RUN_DIR")
        differ, errors = report.blocks(args.check or args.update, update=bool(args.update))
        for line in differ + errors:
            print(line, file=sys.stderr)
        return 1 if errors or (differ and args.check) else 0
    if args.archive:
        if len(args.run_dirs) != 1:
            raise RunDirError(f"--archive DEST takes one RUN_DIR, got {len(args.run_dirs)}")
        copies = report.archive(args.archive, args.run_dirs[0])
        print(f"{len(copies)} files of {args.run_dirs[0]} -> {args.archive}")
        return 0
    if args.suite and args.run_dirs:
        raise RunDirError("--suite DIR reads a benchmark directory; name no RUN_DIR beside it")
    text = report.render(args, fmt=args.format)
    if args.out:
        args.out.write_text(text)
    else:
        sys.stdout.write(text)
    return 0


REPORT_HELP = """A results table from run directories' results.json (trains nothing): rows are the
methods x the settings that differ between the runs (runs that agree on all but seed and
parallel pool their seeds; lazy Q's rows also name evaluate --set's policy settings),
columns each task rate as mean [95 % CI] over the seeds, the seeds, the budget and the
training seconds per seed; a line under the table names the task, the seeds, the CI and
the command.  Markdown report blocks, <!-- report ARGS --> ... <!-- /report -->, hold what
`report ARGS` writes, ARGS' paths relative to the Markdown file's git root: --check and
--update regenerate them."""


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m lazyq_jax", description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    methods_help = (f"comma-separated methods: {', '.join(METHODS)}; a baseline may take options, "
                    "e.g. iql:temperature=10:budget=4 (budget: multiples of lazy Q's gradient steps)")

    p = sub.add_parser("collect", help="collect (or reuse) the task's dataset into the run directory")
    _add_common(p)
    p.add_argument("--seeds", type=int, default=0, help="collect for this many seeds (default: the "
                   "config's seed)")
    p.add_argument("--first-seed", type=int, default=0)
    p.set_defaults(func=cmd_collect)

    p = sub.add_parser("train", help="one seed: data, training with a checkpoint per block, "
                       "evaluation, figures")
    _add_common(p)
    _add_resume(p)
    p.add_argument("--methods", default="lazy", help=f"{methods_help} (default lazy)")
    p.add_argument("--no-eval", action="store_true", help="skip the evaluation after training")
    p.set_defaults(func=cmd_train)

    p = sub.add_parser("study", help="several seeds at once, each phase one program; mean and "
                       "95 %% CI per method -> RUN_DIR/results.json, summary.md, figures/")
    _add_common(p)
    _add_resume(p)
    p.add_argument("--seeds", type=int, default=8, help="number of seeds (default 8)")
    p.add_argument("--first-seed", type=int, default=0,
                   help="seeds are first-seed .. first-seed + seeds - 1 (default 0)")
    p.add_argument("--methods", default="lazy", help=f"{methods_help} (default lazy)")
    p.set_defaults(func=cmd_study)

    p = sub.add_parser("benchmark", help="every dataset of a benchmark suite, resumably, into one "
                       "directory: RUN_DIR/<dataset>/ runs, RUN_DIR/results.json and results.md")
    p.add_argument("suite", help=f"one of {', '.join(tasks.SUITES)}")
    p.add_argument("--datasets", default=None, help="comma-separated datasets of the suite (default all; "
                   "OGBench's ids, with or without -v0)")
    p.add_argument("--preset", default="paper", help="each dataset's preset (default paper; smoke: tiny)")
    p.add_argument("--run-dir", type=Path, default=None, help="the benchmark directory (default "
                   f"runs/bench_SUITE); resumed when it exists; {LOCK_HELP}")
    p.add_argument("--set", action="append", metavar="FIELD=VALUE",
                   help="override a config field of every dataset, e.g. train.cycles=100 (repeatable)")
    p.add_argument("--seeds", type=int, default=3, help="number of seeds (default 3); seeds the directory "
                   "does not hold yet train as a new group beside the earlier ones, and the table pools them")
    p.add_argument("--first-seed", type=int, default=0)
    p.add_argument("--methods", default="lazy", help=f"{methods_help} (default lazy)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.set_defaults(func=cmd_benchmark)

    for name in ("evaluate", "plot"):
        p = sub.add_parser(name, help=("reload a trained run, evaluate every method again, write "
                                       "eval.json, results.json and figures" if name == "evaluate" else
                                       "redraw the figures and animations of a trained run "
                                       "(re-runs the deterministic evaluation)"))
        p.add_argument("--run-dir", type=Path, required=True,
                       help=f"a run directory of train or study; {LOCK_HELP}")
        p.add_argument("--methods", default=None, help="only these methods (default: all the run's)")
        p.add_argument("--set", action="append", metavar="FIELD=VALUE",
                       help="override an evaluation setting (eval.*, e.g. eval.seed=3) or one of lazy Q's "
                       f"policy settings ({', '.join(POLICY_FIELDS)}; the results name them) "
                       "(repeatable)")
        p.add_argument("--no-figures", action="store_true",
                       help=argparse.SUPPRESS if name == "plot" else "only results.json")
        p.add_argument("--no-progress", action="store_true", help="no progress bars")
        p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser("report", parents=[report.arguments(argparse.ArgumentParser(add_help=False))],
                       help="a results table (Markdown or JSON) from run directories; trains nothing",
                       description=REPORT_HELP, usage="%(prog)s RUN_DIR [RUN_DIR ...] [--methods M,...] "
                       "[--paired] [--per-goal] [--format md|json] [--out FILE]\n"
                       "       %(prog)s --archive DEST RUN_DIR\n       %(prog)s --check FILE [FILE ...]\n"
                       "       %(prog)s --update FILE [FILE ...]")
    p.add_argument("--format", choices=("md", "json"), default="md", help="Markdown (default) or JSON")
    p.add_argument("--out", type=Path, default=None, help="write the table here (default: stdout)")
    what = p.add_mutually_exclusive_group()
    what.add_argument("--archive", type=Path, metavar="DEST", help="copy only the small JSON files report "
                      "reads of RUN_DIR (run.json, results.json, each method's method.json, timings.json, "
                      "eval.json; never checkpoints, data or figures) into DEST, e.g. results/<name>")
    what.add_argument("--check", type=Path, nargs="+", metavar="FILE", help="regenerate every report block "
                      "of these Markdown files; exit 1 naming each block that differs or cannot be made")
    what.add_argument("--update", type=Path, nargs="+", metavar="FILE", help="rewrite those blocks in place")
    p.set_defaults(func=cmd_report)

    p = sub.add_parser("config", help="print the resolved config as JSON")
    _add_common(p)
    p.set_defaults(func=lambda a: print(json.dumps(to_dict(_config(a)), indent=1)))
    args = parser.parse_args(argv)
    try:
        force_host_devices()  # LAZYQ_HOST_DEVICES, before JAX starts its backends
        enable_compilation_cache()
        code = args.func(args)
    except ConfigError as e:
        parser.exit(2, f"config error: {e}\n")
    except (CheckpointError, DatasetError, RunDirError) as e:
        parser.exit(2, f"error: {e}\n")
    return code or 0


if __name__ == "__main__":
    sys.exit(main())
