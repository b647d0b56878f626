# `make demo` and `make test` are the two commands of the README: each does all set-up.
PY ?= python3

setup:
	$(PY) -m pip install -q torch==2.13.0 -e '.[dev]'

demo: setup
	fastenerf demo --out runs/demo

test: setup
	$(PY) -m pytest -q tests

lint:
	ruff check . && ruff format --check .

.PHONY: setup demo test lint
