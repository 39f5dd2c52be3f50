# Two commands on a fresh machine:  `make demo`  and  `make test`.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
OUT ?= out

.PHONY: setup demo test test-slow bench clean

# torch comes with the `bio` extra (the biological front end and TV depth; the tests need it). Its default
# Linux build brings GBs of CUDA libraries, so its CPU build goes in first where pip is offered one: pip's
# dry run says which build it would take (a CUDA build requires nvidia-* packages).
TORCH := torch==2.13.0
CPU_BUILD := import json, sys; m = json.load(open(sys.argv[1]))["install"][0]["metadata"]; \
	sys.exit(any(r.startswith("nvidia-") for r in m.get("requires_dist") or []))

$(BIN)/lobula: pyproject.toml
	$(PY) -m venv $(VENV)
	@if $(BIN)/pip show -q torch 2>/dev/null; then :; \
	elif $(BIN)/pip install -q --dry-run --ignore-installed --no-deps --only-binary :all: \
			--report $(VENV)/torch-plan.json "$(TORCH)" && $(BIN)/python -c '$(CPU_BUILD)' $(VENV)/torch-plan.json; then \
		echo "$(BIN)/pip install $(TORCH) (CPU build)"; $(BIN)/pip install -q --only-binary :all: "$(TORCH)"; \
	else \
		echo "make setup: pip is offered no CPU build of $(TORCH) here, so .[bio] brings torch with CUDA (GBs)." \
			"For the CPU build instead: rm -rf $(VENV) && $(PY) -m venv $(VENV) &&" \
			"$(BIN)/pip install torch --index-url https://download.pytorch.org/whl/cpu && make setup"; \
	fi
	$(BIN)/pip install -q -c constraints.txt -e ".[test,bio]"
	touch $(BIN)/lobula

setup: $(BIN)/lobula

# The scene's velocity profile: the recorded FLIVVER run when ../shared/data/flivver_d435i/velocity.csv
# is beside the clone; on a fresh clone without it, the built-in synthetic profile
# (stimuli.track.builtin_profile: 3 s at rest, then forward and backward sweeps), so the demo runs
# anywhere. `lobula scene` prints which ("profile: ..."); run.png plots the truth it was given.
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

# The documentation site (mkdocs.yml, docs/) into site/, strict: any warning fails the build. The CLI
# reference is generated from the parsers and the API pages from the docstrings at build time.
.PHONY: docs
docs: setup
	$(BIN)/pip install -q -c constraints.txt -e ".[docs]"
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict
