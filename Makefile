# Two commands do all the set-up: `make train` and `make test`.
# Each creates .venv/ and installs the package (editable) on first use; the
# stamp file makes re-runs skip the install unless pyproject.toml changed.
# `make train` resumes its run directory: a finished run is only re-evaluated;
# ARGS="--overwrite" starts it afresh, RUN=runs/other uses another directory.
# `make benchmark` runs OGBench's pointmaze suite (SEEDS default 3; BENCH_METHODS default lazy, e.g. lazy,gcivl,hiql).
# TASK=arm (or arm-long: the disk anywhere, long-horizon task too) trains the arm
# (joint-space pushing) in runs/$(TASK), resuming it as `make train` does; `make study
# TASK=arm METHODS=lazy,iql,td3bc` studies any task and methods.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
RUN ?= runs/paper
ARGS ?=

TASK ?= push
ifeq ($(TASK),push)
TRAIN_FLAGS = --run-dir $(RUN) --resume
else
TRAIN_FLAGS = --task $(TASK) --run-dir $(if $(filter command line,$(origin RUN)),$(RUN),runs/$(TASK)) --resume
endif

SEEDS ?= 8
METHODS ?= lazy
STUDY ?= $(if $(filter push,$(TASK)),runs/study_paper,runs/study_$(TASK))

SUITE ?= ogbench-pointmaze
BENCH_METHODS ?= lazy

.PHONY: train test bench benchmark eval study clean

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

train: $(STAMP)
	$(PY) -m lazyq_jax train $(TRAIN_FLAGS) $(ARGS)

study: $(STAMP)
	$(PY) -m lazyq_jax study --task $(TASK) --preset paper --seeds $(SEEDS) --methods $(METHODS) --run-dir $(STUDY) --resume $(ARGS)

# Every dataset of a benchmark suite (OGBench's eight pointmaze datasets), resumably, into
# runs/bench_$(SUITE); its table: runs/bench_$(SUITE)/results.md.
benchmark: $(STAMP)
	$(PY) -m lazyq_jax benchmark $(SUITE) --seeds $(if $(filter command line environment,$(origin SEEDS)),$(SEEDS),3) --methods $(BENCH_METHODS) $(ARGS)

eval: $(STAMP)
	$(PY) -m lazyq_jax evaluate --run-dir $(RUN) $(ARGS)

# The suite runs its files on up to 4 worker processes (one per core; pytest-xdist):
# each file stays on one worker, so its compiled fixtures are built once.
# TEST_WORKERS=0 runs it in this process.
TEST_WORKERS ?= auto
test: $(STAMP)
	$(PY) -m pytest -q -n $(TEST_WORKERS) --maxprocesses 4 --dist loadfile --no-loadscope-reorder $(ARGS)

bench: $(STAMP)
	$(PY) experiments/bench_collect.py
	$(PY) experiments/bench_neighbours.py
	$(PY) experiments/bench_lstsq.py
	$(PY) experiments/bench_train.py
	$(PY) experiments/bench_devices.py

clean:
	rm -rf $(VENV) build *.egg-info
