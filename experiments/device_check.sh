#!/usr/bin/env bash
# The prepared check for a lent GPU (the `device` tool: 15 minutes of device time in all, one
# command of at most 10 minutes).  What the issues ask of a device, as parts run in the order
# given, each bounded so that what finished comes back even when a later part runs out of time:
#
#   bash experiments/device_check.sh lazy     (~9 minutes on an H200)
#     OGBench's pointmaze (issue 24): lazy Q, 3 seeds vmapped, trained and evaluated, then
#     GCIVL's steps a second at OGBench's 3 x 512 and batch 1024 timed on the same data
#     (experiments/pointmaze_budget.py --calibrate-only); the run directory (without data
#     and checkpoints) is copied to $OUT/pm.tgz every 20 s, the log to $OUT/pointmaze.log;
#     then the search and the query below with the time left.
#   bash experiments/device_check.sh gcivl STEPS   (~3 minutes)
#     GCIVL for STEPS steps (the rate printed by `lazy` times lazy Q's time, capped by what is
#     left) on the same seeds' data, 3 seeds vmapped, evaluated: $OUT/pm2.tgz.
#   bash experiments/device_check.sh search [query] [arm] [layouts]   (any of these, in order)
#     search: the paper-scale neighbour search (issue 22, experiments/bench_neighbours.py),
#       build_index on the device and on the host in the same run (bitwise compared);
#     query: the policy's per-step query (bench_neighbours.py --cases q3,q5);
#     arm: `arm` at 10x the paper's random moves (issue 23's data lever: 50,000 starts x 2
#       moves, each stored with 10 goals: the rows, and so the training's cost, of `static4x`),
#       ARM_SEEDS (default 5) seeds vmapped, trained and evaluated: $OUT/arm_50000_10.tgz;
#       ARM_RUNS="20000:25 50000:25" runs other STARTS:GOALS one after the other;
#     layouts: the policy query's compile on the GPU for `static4x` data (its evaluation's
#       compile ran over 6 minutes on an H200, docs/arm.md): the 5 seeds' data collected
#       (the study stopped once they are written), then experiments/policy_layouts.py
#       (each seed's layout; the stacked query compiled on seed 1's and on seed 0's layout).
#
# Packages the device image lacks (MuJoCo, MJX, ogbench) and our pinned flax/optax/orbax/chex
# travel as wheels in .whl (git-ignored; docs/performance.md "One GPU (NVIDIA H200...)" has the
# command that downloads them).  Through the device tool, from the repository root:
#
#   run(command="bash experiments/device_check.sh lazy", carry=[".whl"], timeout_s=600)
#   run(command="bash experiments/device_check.sh gcivl 91895", carry=[".whl"], timeout_s=250)
#   run(command="bash experiments/device_check.sh search arm", carry=[".whl"], timeout_s=600)
#
# Environment: DEADLINE_S (default 585: seconds after which nothing new starts), PM_MAX_S
# (default 100: the cap on the baselines' budget printed by `lazy`), PM_SEEDS (default 3),
# ARM_SEEDS (default 5), ARM_RUNS, ARM_EXTRA (more study options); for a dry run on a CPU:
# PM_EXTRA="--preset smoke --calibrate 20" SEARCH_N=100000 QUERY_EXTRA="--n-states 2000"
# ARM_RUNS=500:10 ARM_EXTRA="--set train.cycles=1" SKIP_WHEELS=1
# PATH=$PWD/.venv/bin:$PATH bash experiments/device_check.sh lazy   (or search query arm)
# Lazy Q at OGBench's sample budget (1024 one-epoch cycles over the 1M rows = the samples of
# 1M steps of batch 1024): PM_EXTRA="--set train.cycles=1024" ... lazy.  Not run on a device
# yet; from the 300 cycles' H200 times (search 69 s + training 103 s) about 69 + 352 s for 3
# seeds, near the `lazy` part's limit (DEADLINE_S - 100 s): PM_SEEDS=2 leaves a margin.
set -u
USAGE="usage: device_check.sh lazy | gcivl STEPS | search | query | arm | layouts (any of the last four, in order)"
PART=${1:?"$USAGE"}
T0=$(date +%s)
DEADLINE_S=${DEADLINE_S:-585}
PM_MAX_S=${PM_MAX_S:-100}
PM_SEEDS=${PM_SEEDS:-3}
ARM_SEEDS=${ARM_SEEDS:-5}
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
    # GCIVL for the given steps, 3 seeds vmapped, OGBench's evaluation
    STEPS=${2:?"usage: device_check.sh gcivl STEPS"}
    ( while sleep 20; do snapshot pm2; done ) &
    SNAP=$!
    timeout "$(left)" python3 -m lazyq_jax study --task pointmaze --seeds "$PM_SEEDS" \
        --methods "gcivl:steps=$STEPS" --run-dir /tmp/pm2 --no-progress ${PM_EXTRA:-} > "$OUT/pm2.log" 2>&1
    log "gcivl: exit $?"
    kill $SNAP 2>/dev/null; snapshot pm2
    exit 0
fi
if [ "$PART" = lazy ]; then
    # 1. pointmaze: lazy Q, 3 seeds vmapped, OGBench's evaluation; then GCIVL's rate on the same data
    ( while sleep 20; do snapshot pm; done ) &
    SNAP=$!
    log "pointmaze: $(left) s left"
    timeout $(( $(left) - 100 )) python3 experiments/pointmaze_budget.py --run-dir /tmp/pm --seeds "$PM_SEEDS" \
        --methods gcivl --max-seconds "$PM_MAX_S" --calibrate 300 --calibrate-only ${PM_EXTRA:-} \
        > "$OUT/pointmaze.log" 2>&1
    log "pointmaze: exit $?"
    kill $SNAP 2>/dev/null; snapshot pm
fi

# the neighbour search and the policy query on the GPU (the 2-core CPU's figures: docs/performance.md)
search() {
    if [ "$(left)" -gt 30 ]; then
        log "search: $(left) s left"
        timeout $(( $(left) < 90 ? $(left) : 90 )) python3 experiments/bench_neighbours.py --repeats 3 \
            --skip-baseline --check 60 --n "${SEARCH_N:-1000000}" --build auto,host > "$OUT/search.log" 2>&1
        log "search: exit $?"
    fi
}
query() {
    if [ "$(left)" -gt 20 ]; then
        log "query: $(left) s left"
        timeout "$(left)" python3 experiments/bench_neighbours.py --cases q3,q5 --repeats 2 ${QUERY_EXTRA:-} \
            > "$OUT/query.log" 2>&1
        log "query: exit $?"
    fi
}
# `arm` from static4x with STARTS starts (2 moves each) stored with GOALS goals, for each
# STARTS:GOALS of ARM_RUNS (default 50000:10, 10x the moves), ARM_SEEDS seeds vmapped
arm() {
    for run in ${ARM_RUNS:-50000:10}; do
        local starts=${run%:*} goals=${run#*:} name=arm_${run%:*}_${run#*:}
        ( while sleep 20; do snapshot "$name"; done ) &
        local snap=$!
        log "arm $starts starts x $goals goals: $(left) s left"
        timeout "$(left)" python3 -m lazyq_jax study --task arm --preset static4x \
            --set collect.n_starts="$starts" --set collect.n_goals="$goals" --seeds "$ARM_SEEDS" \
            --methods lazy --run-dir "/tmp/$name" --no-progress ${ARM_EXTRA:-} > "$OUT/$name.log" 2>&1
        log "arm $starts x $goals: exit $?"
        kill $snap 2>/dev/null; snapshot "$name"
    done
}
# the policy query's compile for static4x's data on this device (seeds 0-4)
layouts() {
    log "layouts: $(left) s left"
    rm -rf /tmp/arm_layouts
    python3 -m lazyq_jax study --task arm --preset static4x --seeds 5 --methods lazy \
        --run-dir /tmp/arm_layouts --no-progress ${ARM_EXTRA:-} > "$OUT/layouts_data.log" 2>&1 &
    local study=$!
    while kill -0 $study 2>/dev/null && ! grep -q "lazy: block\|training" "$OUT/layouts_data.log" \
          && [ "$(ls /tmp/arm_layouts/data/4/dataset.npz 2>/dev/null)" = "" ]; do sleep 2; done
    sleep 5; kill $study 2>/dev/null; wait $study 2>/dev/null
    log "layouts: data written"
    timeout "$(left)" python3 experiments/policy_layouts.py /tmp/arm_layouts --seeds 0,1,2,3,4 \
        --rotated-first > "$OUT/layouts.log" 2>&1
    log "layouts: exit $?"
}

if [ "$PART" = lazy ]; then
    search; query
else
    for p in "$@"; do
        case "$p" in search|query|arm|layouts) "$p" ;; *) echo "$USAGE"; exit 2 ;; esac
    done
fi
log "done"
