"""Per-phase speed-up from more host devices (issue: the pipeline sharded over a mesh).

For each device count (default 1 and 2) a fresh process (``XLA_FLAGS`` must be set
before JAX starts) runs the phases of ``make train`` on the same config and seed:

* collection: :func:`lazyq_jax.collect` over the mesh (first call incl. compile, then
  the same collection again: steady state, the compiled kernel is cached);
* neighbour search: lazy Q's ``prepare`` (the neighbourhoods) on that dataset
  (first, then steady);
* training: one jitted cycle of :func:`lazyq_jax.train.make_train` (``epochs``
  epochs + targets; first incl. compile, then the median of ``--cycles`` more).

All counts run in the same invocation, one after the other, ``--repeats`` times in
alternating order (1, 2, 1, 2, ...: this machine's speed drifts by 10-30 %); the parent
prints the median of every phase, the speed-up of each count over the first, and
checks that the datasets and the neighbourhoods are bitwise equal.  Whole ``make train`` timings are a separate
command (see the README): ``LAZYQ_HOST_DEVICES=N make train``.

    .venv/bin/python experiments/bench_devices.py [--devices 1 2] [--preset paper] [--cycles 2]
                                                  [--repeats 2]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile


def worker(n_dev: int, preset: str, cycles: int, out: str) -> None:
    os.environ["XLA_FLAGS"] = f"--xla_force_host_platform_device_count={n_dev}"
    import dataclasses

    import jax
    import numpy as np
    from _common import timed as timed_call  # the script's own folder is on sys.path

    from lazyq_jax import agents, tasks
    from lazyq_jax.config import ParallelConfig
    from lazyq_jax.keys import purpose_key
    from lazyq_jax.parallel import make_mesh, put, replicated

    task = tasks.get("push")
    config = dataclasses.replace(tasks.preset("push", preset), parallel=ParallelConfig(devices=n_dev))
    mesh = make_mesh(config.parallel)
    agent = agents.make("lazy", agents.LazyConfig(train=config.train, neighbours=config.neighbours),
                        problem=task.problem(config), mesh=mesh)
    times = {}

    def timed(name, fn, repeats=1):
        result, times[f"{name}_first"], times[f"{name}_steady"] = timed_call(fn, repeats=repeats)
        return result

    data = timed("collect", lambda: task.collect(purpose_key(0, "collect"), config, mesh=mesh,
                                                 progress=False))
    idx = timed("search", lambda: agent.prepare(0, data, data.size, 0).idx)
    trainer = agent.trainer
    data_r = put(data, replicated(mesh))
    state0 = put(trainer.init(purpose_key(0, "train"), data), replicated(mesh))
    run_cycle = jax.jit(trainer.run_cycle)
    timed("train_cycle", lambda: run_cycle(state0, data_r, idx)[0].params, repeats=cycles)
    np.savez(out, s=np.asarray(data.s), s_next=np.asarray(data.s_next), r=np.asarray(data.r),
             idx=np.asarray(idx))
    print(json.dumps(times), flush=True)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--devices", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--preset", default="paper")
    ap.add_argument("--cycles", type=int, default=2, help="steady training cycles to time")
    ap.add_argument("--repeats", type=int, default=2, help="processes per device count")
    ap.add_argument("--worker", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--out", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        worker(args.worker, args.preset, args.cycles, args.out)
        return
    import numpy as np

    runs, files = {n: [] for n in args.devices}, {}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.repeats):
            for n in args.devices:
                files[n] = os.path.join(tmp, f"d{n}.npz")
                proc = subprocess.run([sys.executable, __file__, "--worker", str(n), "--preset",
                                       args.preset, "--cycles", str(args.cycles), "--out", files[n]],
                                      check=True, stdout=subprocess.PIPE, text=True)
                runs[n].append(json.loads(proc.stdout.strip().splitlines()[-1]))
                print(f"repeat {r + 1}, {n} device(s): " + ", ".join(
                    f"{k} {v:.2f}" for k, v in runs[n][-1].items()), flush=True)
        ref = np.load(files[args.devices[0]])
        for n in args.devices[1:]:
            other = np.load(files[n])
            same = {k: bool(np.array_equal(ref[k], other[k])) for k in ref.files}
            print(f"{n} vs {args.devices[0]} devices: bitwise equal {same}")
    results = {n: {k: statistics.median(run[k] for run in runs[n]) for k in runs[n][0]}
               for n in args.devices}
    base = results[args.devices[0]]
    print(f"\nmedians of {args.repeats} process(es) per device count")
    print(f"\n{'phase':<20}" + "".join(f"{f'{n} dev (s)':>12}" for n in args.devices)
          + "".join(f"{f'x{n}/{args.devices[0]}':>10}" for n in args.devices[1:]))
    for name in base:
        row = f"{name:<20}" + "".join(f"{results[n][name]:>12.2f}" for n in args.devices)
        row += "".join(f"{base[name] / results[n][name]:>10.2f}" for n in args.devices[1:])
        print(row)


if __name__ == "__main__":
    main()
