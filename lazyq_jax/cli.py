"""``python -m lazyq_jax collect|train ...``: parse, then call library functions.

Any config field can be overridden: ``--set train.width=128 --set seed=3``.
Compiled programs are cached on disk (``LAZYQ_COMPILE_CACHE``, see
:func:`lazyq_jax.parallel.enable_compilation_cache`), so a second run compiles little.
Devices: ``--set parallel.devices=N`` (default all), ``LAZYQ_HOST_DEVICES=N`` for N
CPU devices, ``--set parallel.distributed=true`` or ``LAZYQ_DISTRIBUTED=1`` on a cluster.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from lazyq_jax.checkpoint import CheckpointError, load_checkpoint
from lazyq_jax.config import PRESETS, Config, ConfigError, override, preset, to_dict
from lazyq_jax.data import DatasetError
from lazyq_jax.evaluate import EvalError, evaluate_run
from lazyq_jax.parallel import (enable_compilation_cache, force_host_devices, is_main_process,
                                maybe_initialize_distributed)
from lazyq_jax.pipeline import RunDirError, fit, mesh_for, prepare_dataset


def _config(args) -> Config:
    config = override(preset(args.preset), args.set or [])
    maybe_initialize_distributed(config.parallel)  # before anything touches a device
    return config


def _add_common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--run-dir", type=Path, default=None,
                   help="output directory (default runs/<preset>)")
    p.add_argument("--preset", default="paper", help=f"one of {sorted(PRESETS)} (default paper)")
    p.add_argument("--set", action="append", metavar="FIELD=VALUE",
                   help="override a config field, e.g. train.width=128 (repeatable)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")


def cmd_collect(args) -> None:
    config = _config(args)
    run_dir = args.run_dir or Path("runs") / args.preset
    run_dir.mkdir(parents=True, exist_ok=True)
    prepare_dataset(config, run_dir, progress=not args.no_progress, mesh=mesh_for(config))
    summary = run_dir / "dataset_summary.json"
    if summary.exists() and is_main_process():
        print(summary.read_text())


def cmd_train(args) -> None:
    if args.task != "push":
        from lazyq_jax.arm_task import ARM_TASKS, check_arm_overrides, fit_arm

        check_arm_overrides(args.set or [])
        config = _config(args)
        run_dir = args.run_dir or Path("runs") / f"{args.task}_{args.preset}"
        t = time.perf_counter()
        fit_arm(config, run_dir, task=ARM_TASKS[args.task], resume=args.resume,
                overwrite=args.overwrite, progress=not args.no_progress, evaluate=not args.no_eval)
        print(f"arm: done in {time.perf_counter() - t:.1f} s; run directory: {run_dir}")
        return
    config = _config(args)
    run_dir = args.run_dir or Path("runs") / args.preset
    t = time.perf_counter()
    if config.online.rounds:  # online lazy Q: the agent gathers its own pushes
        from lazyq_jax.online import evaluate_online, fit_online

        state, data, n_valid, fns = fit_online(config, run_dir, resume=args.resume,
                                               overwrite=args.overwrite, progress=not args.no_progress)
        print(f"trained in {time.perf_counter() - t:.1f} s")
        if not args.no_eval:
            r = evaluate_online(config, run_dir, state, data, n_valid, fns)
            a, b = r["protocol_a"], r["protocol_b"]
            print(f"protocol A (goal directions): axis correct {a['axis_correct_rate']:.1%}, all "
                  f"{a['overall_correct_rate']:.1%}; protocol B (long horizon): {b['successes']}/"
                  f"{b['rollouts']} ({r['seconds']:.0f} s) -> {run_dir / 'eval' / 'results.json'}")
        print(f"run directory: {run_dir}")
        return
    fit(config, run_dir, resume=args.resume, overwrite=args.overwrite,
        progress=not args.no_progress)
    print(f"trained in {time.perf_counter() - t:.1f} s")
    if not args.no_eval and is_main_process():  # evaluation runs on one device of process 0
        _evaluate(run_dir, [])
    print(f"run directory: {run_dir}")


def _evaluate(run_dir: Path, assignments: list[str], figures: bool = True) -> None:
    bad = [a for a in assignments if not a.strip().startswith("eval.")]
    if bad:
        raise ConfigError(f"evaluate takes only eval.* overrides (the run's own config is used), "
                          f"got {bad}")
    _, config = load_checkpoint(run_dir / "checkpoints")
    eval_config = override(config, assignments).eval
    results = evaluate_run(run_dir, eval_config, figures=figures)
    a, b = results["protocol_a"], results["protocol_b"]
    print(f"protocol A (goal directions): axis correct {a['axis_correct_rate']:.1%}, all "
          f"{a['overall_correct_rate']:.1%}; protocol B (long horizon): {b['successes']}/"
          f"{b['rollouts']} ({results['seconds']:.0f} s) -> {run_dir / 'eval' / 'results.json'}")
    if figures:
        print(f"figures: {run_dir / 'figures'}")


def cmd_study(args) -> None:
    from lazyq_jax.study import run_study

    config = _config(args)
    run_dir = args.run_dir or Path("runs") / f"study_{args.preset}"
    if args.seeds < 1:
        raise ConfigError(f"--seeds must be >= 1, got {args.seeds}")
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    run_study(config, run_dir, seeds=seeds, methods=methods, resume=args.resume,
              overwrite=args.overwrite, progress=not args.no_progress)


def cmd_evaluate(args) -> None:
    _evaluate(args.run_dir, args.set or [], figures=not args.no_figures)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m lazyq_jax", description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("collect", help="collect the random-push dataset into the run directory")
    _add_common(p)
    p.set_defaults(func=cmd_collect)
    p = sub.add_parser("train", help="collect (or reuse), find neighbours, train, checkpoint")
    _add_common(p)
    p.add_argument("--resume", action="store_true",
                   help="continue from the newest checkpoint (start afresh if there is none)")
    p.add_argument("--overwrite", action="store_true",
                   help="delete the run directory's checkpoints and train afresh")
    p.add_argument("--no-eval", action="store_true", help="skip the evaluation after training")
    p.add_argument("--task", choices=("push", "arm", "arm-long"), default="push",
                   help="push: the finger (paper); arm: a 3-link arm pushing in joint space, the "
                   "disk at the origin (state q; protocol A); arm-long: the disk anywhere, its "
                   "position in the state (protocol A and the long-horizon task)")
    p.set_defaults(func=cmd_train)
    p = sub.add_parser("study", help="the whole pipeline for several seeds at once; mean and 95 %% CI "
                       "per method -> RUN_DIR/results.json, summary.md, figures/")
    _add_common(p)
    p.add_argument("--seeds", type=int, default=8, help="number of seeds (default 8)")
    p.add_argument("--first-seed", type=int, default=0,
                   help="seeds are first-seed .. first-seed + seeds - 1 (default 0)")
    p.add_argument("--methods", default="lazy",
                   help="comma-separated methods (default lazy): lazy, iql, td3bc, dqn, naf, bc, "
                   "random, scripted; a baseline may take options, e.g. iql:temperature=10:budget=4")
    p.add_argument("--resume", action="store_true", help="continue the study in --run-dir")
    p.add_argument("--overwrite", action="store_true", help="delete the study in --run-dir first")
    p.set_defaults(func=cmd_study)
    for name in ("evaluate", "plot"):
        p = sub.add_parser(name, help="reload a finished run; run both evaluation protocols; write "
                           "eval/results.json and figures/" if name == "evaluate" else
                           "redraw figures/ of a finished run (reruns the deterministic evaluation)")
        p.add_argument("--run-dir", type=Path, required=True, help="a run directory made by train")
        p.add_argument("--set", action="append", metavar="eval.FIELD=VALUE",
                       help="override an evaluation setting, e.g. eval.seed=3 (repeatable)")
        p.add_argument("--no-figures", action="store_true", help=argparse.SUPPRESS
                       if name == "plot" else "only results.json")
        p.set_defaults(func=cmd_evaluate)
    p = sub.add_parser("config", help="print the resolved config as JSON")
    _add_common(p)
    p.set_defaults(func=lambda a: print(json.dumps(to_dict(_config(a)), indent=1)))
    args = parser.parse_args(argv)
    try:
        force_host_devices()  # LAZYQ_HOST_DEVICES, before JAX starts its backends
        enable_compilation_cache()
        args.func(args)
    except ConfigError as e:
        parser.exit(2, f"config error: {e}\n")
    except (CheckpointError, DatasetError, EvalError, RunDirError) as e:
        parser.exit(2, f"error: {e}\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
