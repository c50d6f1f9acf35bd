# `make run` and `make test` set up what they need first (see scripts/setup.sh).
PY := .venv/bin/python
STAMP := .venv/.setup-stamp

.PHONY: setup run test bench dvc clean-store

setup: $(STAMP)

$(STAMP): pyproject.toml scripts/setup.sh
	bash scripts/setup.sh
	touch $(STAMP)

run: setup
	.venv/bin/pipeline run

test: setup
	$(PY) -m pytest -q

bench: setup
	$(PY) benchmarks/engine.py

dvc: setup
	.venv/bin/pipeline dvc
