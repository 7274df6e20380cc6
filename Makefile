# Two entry points for a new user: `make demo` (the main job) and `make test` (the tests).
# Each creates .venv and installs the pinned stack on first use.
PYTHON ?= python3.11
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	# torch first and pinned: an unpinned torch pulls several GB of CUDA wheels.
	$(PY) -m pip install --quiet "torch==2.13.0"
	$(PY) -m pip install --quiet -e ".[test]"
	touch $(STAMP)

.PHONY: install demo test test-slow bench
install: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/offdyn-bench demo

# The default run: one pytest-xdist worker per core, at most 4 (each holds torch and MuJoCo;
# more would mostly add memory). worksteal: a worker that runs out takes queued tests from the
# other, so one long module does not leave a core idle at the end (on 2 idle cores 770 s, against
# 912 s for --dist loadgroup with the Ray modules and the finished-sweep readers each grouped on one
# worker). make test-slow stays in one process: its long trainings were not run under xdist.
PARALLEL := -n auto --maxprocesses 4 --dist worksteal

test: $(STAMP)
	$(PY) -m pytest -q $(PARALLEL)

test-slow: $(STAMP)
	$(PY) -m pytest -q -m slow

# Speed figures quoted in the README: each measures the suite against its reference in one run.
bench: $(STAMP)
	$(PY) -m pip install --quiet -e ".[test,bench]"
	$(PY) benchmarks/env_step_rate.py
	$(PY) benchmarks/bench_sac.py --rounds 5 --updates-per-round 100 --seed-steps 300 --seeds 5 --seed-rounds 2 --hidden 256 64
	$(PY) benchmarks/bench_diagnose.py
	$(PY) benchmarks/bench_datasets.py
	$(PY) benchmarks/bench_statistics.py
	$(PY) benchmarks/bench_cli_startup.py --repeats 11
	$(PY) -m pytest -q -m benchmark --benchmark-enable
