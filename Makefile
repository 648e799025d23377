# The two commands of the README: `make demo` and `make test`. Both set up a fresh machine first.
VENV ?= .venv
PY := $(VENV)/bin/python
PYTEST_ARGS ?= -q

.PHONY: setup demo test previews clean

setup:
	bash tools/setup.sh $(VENV)

demo: setup
	$(PY) -m mi_twopass demo

test: setup
	$(PY) -m pytest $(PYTEST_ARGS) tests

previews: setup
	$(PY) docs/previews/make_previews.py

clean:
	rm -rf out .cache .pytest_cache
