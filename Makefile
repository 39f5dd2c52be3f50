# Two commands on a fresh machine:  `make demo`  and  `make test`.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
OUT ?= out

.PHONY: setup demo test test-slow bench clean

$(BIN)/lobula: pyproject.toml
	$(PY) -m venv $(VENV)
	# The CPU build of torch first: an unpinned torch would pull GBs of CUDA wheels.
	$(BIN)/pip install -q "torch==2.13.0" || $(BIN)/pip install -q "torch>=2.1,<3"
	$(BIN)/pip install -q -e ".[test]"
	touch $(BIN)/lobula

setup: $(BIN)/lobula

# The scene follows the real FLIVVER velocity profile when ../shared is beside the clone,
# else its built-in profile: the demo runs anywhere.
demo: setup
	rm -rf $(OUT)/track
	$(BIN)/lobula scene $(OUT)/track --start 0 --duration 30 --scale 0.5
	$(BIN)/lobula velocity $(OUT)/track --front-end dis --out $(OUT)/run.nc --plot $(OUT)/run.png

# Tests on parallel workers (pytest-xdist; at most 4, each builds its own fixtures): see tests/conftest.py.
test: setup
	$(BIN)/python -m pytest -q -n auto --maxprocesses 4 --dist loadgroup

test-slow: setup
	$(BIN)/python -m pytest -q -m slow -n auto --maxprocesses 4 --dist loadgroup

bench: setup
	$(BIN)/lobula bench

clean:
	rm -rf $(OUT) .pytest_cache
