# `make run` and `make test` set up what they need first (see scripts/setup.sh).
PY := .venv/bin/python
STAMP := .venv/.setup-stamp

TEST_STAMP := .venv/.setup-test-stamp

.PHONY: setup setup-test run test bench baseline dvc clean-store

setup: $(STAMP)

$(STAMP): pyproject.toml constraints.txt scripts/setup.sh
	bash scripts/setup.sh
	touch $(STAMP)

# the tests also need headless Chromium (the report test)
setup-test: $(TEST_STAMP)

$(TEST_STAMP): $(STAMP)
	bash scripts/setup.sh --test
	touch $(TEST_STAMP)

# ARGS: more `pipeline run` arguments, e.g. make run ARGS='--profile ci' (the tests run it so)
run: setup
	.venv/bin/pipeline run --executor process $(ARGS)

test: setup-test
	$(PY) -m pytest -q -n auto --dist loadfile

# every benchmark, then one table of the ratios they measured (benchmarks/run_all.py)
bench: setup
	$(PY) benchmarks/run_all.py

# the regression baseline CI compares against: the ci DAG over 5 seeds and once with restricted
# CPU kernels, each metric's mean and spread (scripts/ci_baseline.py)
baseline: setup
	$(PY) scripts/ci_baseline.py --store artifacts-ci --out baselines/ci.yaml

dvc: setup
	.venv/bin/pipeline dvc
