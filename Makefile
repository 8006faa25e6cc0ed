# One entry point for a new machine: every target builds .venv/ itself.
PYTHON ?= python3.11
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: main demo fit test test-quick lint bench reports screenshots clean

# The locked set (requirements-dev.lock, hashes checked: the image installs the same
# versions from requirements.lock), then the project itself without resolving again.
$(STAMP): pyproject.toml requirements-dev.lock
	@command -v $(PYTHON) >/dev/null || { echo "need $(PYTHON) on PATH"; exit 1; }
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --require-hashes -r requirements-dev.lock
	$(PY) -m pip install --quiet --no-deps -e .
	touch $(STAMP)

# The main job on embedded defaults: simulated machine + gateway, compensated vs not.
main demo: $(STAMP)
	$(PY) -m gateway demo

# Fit a model on the bundled real 46-hour spindle test, with the commands' default
# method (lag-ridge; --method names another).
fit: $(STAMP)
	$(PY) -m gateway fit data/fl_thermal.csv --target ch5_um --store .cache/models

test: $(STAMP)
	bash scripts/test.sh

# Everything but the end-to-end plant runs (tests/conftest.py marks them slow).
test-quick: $(STAMP)
	bash scripts/test.sh -m "not slow"

lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/mypy

# The residual analysis reports of the bundled real data (HTML and plots, git-ignored),
# on the default model (lag-ridge), as `analyze` gives them.
reports: $(STAMP)
	for ch in ch1 ch3 ch5; do \
		$(PY) -m gateway analyze data/fl_thermal.csv --target $${ch}_um --no-progress \
			--report docs/analysis/fl_thermal_$$ch || exit 1; \
	done

# The console screenshots shown by README.md and docs/console.md (docs/img/console-*.png),
# taken by its browser tests; a plain test run leaves docs/img alone.
screenshots: $(STAMP)
	@command -v chromium >/dev/null && command -v chromedriver >/dev/null \
		|| { echo "need chromium and chromedriver: bash scripts/setup-system.sh"; exit 1; }
	SPINDLE_UPDATE_DOCS_IMAGES=1 $(VENV)/bin/pytest -q -p no:cacheprovider tests/test_web_console.py

bench: $(STAMP)
	$(PY) benchmarks/fit_speed.py

clean:
	rm -rf $(VENV) .cache
