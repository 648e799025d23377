# The two commands of the README: `make demo` and `make test`. Both set up a fresh machine first.
VENV ?= .venv
PY := $(VENV)/bin/python
PYTEST_ARGS ?= -q
# e.g. make bench BENCH_ARGS="--budget 10 ../shared/scenes/*/scene.xml --corpus"
BENCH_ARGS ?=

.PHONY: setup demo test bench previews clean

setup:
	bash tools/setup.sh $(VENV)

demo: setup
	$(PY) -m mi_twopass demo

test: setup
	$(PY) -m pytest $(PYTEST_ARGS) tests

# every scenes_xml scene x every integrator, 25 s each: about 24 min on 2 cores (see
# `python -m mi_twopass bench --help`); the report lands in benchmarks/results.md
bench: setup
	$(PY) -m mi_twopass bench $(BENCH_ARGS)

previews: setup
	$(PY) docs/previews/make_previews.py

clean:
	rm -rf out .cache .pytest_cache
