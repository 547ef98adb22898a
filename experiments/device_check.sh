#!/usr/bin/env bash
# The prepared check for a lent GPU (the `device` tool: 15 minutes of device time in all, one
# command of at most 10 minutes).  Everything the issues ask of a device, in one script, each
# stage bounded so that what finished comes back even when a later stage runs out of time:
#
#   1. OGBench's pointmaze (issue 24): lazy Q and GCIVL (OGBench's 3 x 512, batch 1024) on the
#      same data, 3 seeds vmapped, GCIVL for lazy Q's GPU time (capped by PM_MAX_S), through
#      experiments/pointmaze_budget.py; the run directory (without data and checkpoints) is
#      copied to $OUT/pm.tgz every 20 s, the log to $OUT/pointmaze.log.
#   2. The paper-scale neighbour search (issue 22, experiments/bench_neighbours.py) and the
#      policy's per-step query (bench_neighbours_query.py) on the GPU, with what time is left.
#
# Packages the device image lacks (MuJoCo, MJX, ogbench) and our pinned flax/optax/orbax/chex
# travel as wheels in .whl (git-ignored; see docs/performance.md "One GPU" for the command that
# downloads them).  Run through the device tool from the repository root:
#
#   run(command="bash experiments/device_check.sh", carry=[".whl"], timeout_s=600)
#
# Environment: DEADLINE_S (default 585: seconds after which nothing new starts), PM_MAX_S
# (default 100: cap on the baselines' budget), PM_SEEDS (default 3); for a dry run on a CPU
# with a python3 that has the packages: PM_EXTRA="--preset smoke --calibrate 20" SEARCH_N=100000
# QUERY_EXTRA="--n-states 2000" SKIP_WHEELS=1 PATH=$PWD/.venv/bin:$PATH bash experiments/device_check.sh
set -u
T0=$(date +%s)
DEADLINE_S=${DEADLINE_S:-585}
PM_MAX_S=${PM_MAX_S:-100}
PM_SEEDS=${PM_SEEDS:-3}
OUT=${OUT:-/tmp/device_out}
mkdir -p "$OUT"
left() { echo $((DEADLINE_S - ($(date +%s) - T0))); }
log() { echo "[$(($(date +%s) - T0)) s] $*" | tee -a "$OUT/device.log"; }

if [ -z "${SKIP_WHEELS:-}" ]; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
        --target /tmp/site .whl/*.whl || { log "wheel install failed"; exit 1; }
fi
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1
log "installed"
{ nvidia-smi -L; nproc; python3 -c "import jax, flax, mujoco, numpy; print('jax', jax.__version__, jax.devices(), 'flax', flax.__version__, 'mujoco', mujoco.__version__, 'numpy', numpy.__version__)"; } 2>&1 | tee -a "$OUT/device.log"

# 1. pointmaze: lazy Q, then GCIVL at lazy Q's time (capped), 3 seeds vmapped, OGBench's evaluation
PM=/tmp/pm
snapshot() { tar czf "$OUT/pm.tgz.tmp" --exclude=checkpoints --exclude=data -C /tmp pm 2>/dev/null \
             && mv "$OUT/pm.tgz.tmp" "$OUT/pm.tgz"; }
( while sleep 20; do snapshot; done ) &
SNAP=$!
log "pointmaze: $(left) s left"
timeout $(( $(left) - 100 )) python3 experiments/pointmaze_budget.py --run-dir $PM --seeds "$PM_SEEDS" \
    --methods gcivl --max-seconds "$PM_MAX_S" --calibrate 300 ${PM_EXTRA:-} > "$OUT/pointmaze.log" 2>&1
log "pointmaze: exit $?"
kill $SNAP 2>/dev/null; snapshot

# 2. the neighbour search and the policy query on the GPU (the 2-core CPU's figures: docs/performance.md)
if [ "$(left)" -gt 30 ]; then
    log "search: $(left) s left"
    timeout $(( $(left) < 60 ? $(left) : 60 )) python3 experiments/bench_neighbours.py --repeats 3 \
        --skip-scipy --check 60 --n "${SEARCH_N:-1000000}" > "$OUT/search.log" 2>&1
    log "search: exit $?"
fi
if [ "$(left)" -gt 20 ]; then
    log "query: $(left) s left"
    timeout "$(left)" python3 experiments/bench_neighbours_query.py --repeats 2 ${QUERY_EXTRA:-} \
        > "$OUT/query.log" 2>&1
    log "query: exit $?"
fi
log "done"
