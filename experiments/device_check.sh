#!/usr/bin/env bash
# The prepared check for a lent GPU (the `device` tool: 15 minutes of device time in all, one
# command of at most 10 minutes).  What the issues ask of a device, in two commands, each stage
# bounded so that what finished comes back even when a later stage runs out of time:
#
#   bash experiments/device_check.sh lazy     (~9 minutes on an H200)
#     1. OGBench's pointmaze (issue 24): lazy Q, 3 seeds vmapped, trained and evaluated, then
#        GCIVL's steps a second at OGBench's 3 x 512 and batch 1024 timed on the same data
#        (experiments/pointmaze_budget.py --calibrate-only); the run directory (without data
#        and checkpoints) is copied to $OUT/pm.tgz every 20 s, the log to $OUT/pointmaze.log.
#     2. The paper-scale neighbour search (issue 22, experiments/bench_neighbours.py) and the
#        policy's per-step query (bench_neighbours_query.py) on the GPU, with the time left.
#   bash experiments/device_check.sh gcivl STEPS   (~3 minutes)
#     3. GCIVL for STEPS steps (the rate printed by the first command times lazy Q's time,
#        capped by what is left) on the same seeds' data, 3 seeds vmapped, evaluated: $OUT/pm2.tgz.
#
# Packages the device image lacks (MuJoCo, MJX, ogbench) and our pinned flax/optax/orbax/chex
# travel as wheels in .whl (git-ignored; docs/performance.md "One GPU (NVIDIA H200...)" has the
# command that downloads them).  Through the device tool, from the repository root:
#
#   run(command="bash experiments/device_check.sh lazy", carry=[".whl"], timeout_s=600)
#   run(command="bash experiments/device_check.sh gcivl 91895", carry=[".whl"], timeout_s=250)
#
# Environment: DEADLINE_S (default 585: seconds after which nothing new starts), PM_MAX_S
# (default 100: the cap on the baselines' budget printed by the first command), PM_SEEDS
# (default 3); for a dry run on a CPU: PM_EXTRA="--preset smoke --calibrate 20" SEARCH_N=100000
# QUERY_EXTRA="--n-states 2000" SKIP_WHEELS=1 PATH=$PWD/.venv/bin:$PATH bash experiments/device_check.sh lazy
set -u
PART=${1:?"usage: device_check.sh lazy | gcivl STEPS"}
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

# the run directory without data and checkpoints, to $OUT/$1.tgz, every 20 s and at the end
snapshot() { tar czf "$OUT/$1.tgz.tmp" --exclude=checkpoints --exclude=data -C /tmp "$1" 2>/dev/null \
             && mv "$OUT/$1.tgz.tmp" "$OUT/$1.tgz"; }

if [ "$PART" = gcivl ]; then
    # 3. GCIVL for the given steps, 3 seeds vmapped, OGBench's evaluation
    STEPS=${2:?"usage: device_check.sh gcivl STEPS"}
    ( while sleep 20; do snapshot pm2; done ) &
    SNAP=$!
    timeout "$(left)" python3 -m lazyq_jax study --task pointmaze --seeds "$PM_SEEDS" \
        --methods "gcivl:steps=$STEPS" --run-dir /tmp/pm2 --no-progress ${PM_EXTRA:-} > "$OUT/pm2.log" 2>&1
    log "gcivl: exit $?"
    kill $SNAP 2>/dev/null; snapshot pm2
    exit 0
fi
[ "$PART" = lazy ] || { echo "usage: device_check.sh lazy | gcivl STEPS"; exit 2; }

# 1. pointmaze: lazy Q, 3 seeds vmapped, OGBench's evaluation; then GCIVL's rate on the same data
( while sleep 20; do snapshot pm; done ) &
SNAP=$!
log "pointmaze: $(left) s left"
timeout $(( $(left) - 100 )) python3 experiments/pointmaze_budget.py --run-dir /tmp/pm --seeds "$PM_SEEDS" \
    --methods gcivl --max-seconds "$PM_MAX_S" --calibrate 300 --calibrate-only ${PM_EXTRA:-} \
    > "$OUT/pointmaze.log" 2>&1
log "pointmaze: exit $?"
kill $SNAP 2>/dev/null; snapshot pm

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
