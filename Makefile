# Two commands for a fresh machine (see README.md):
#   make demo   set up .venv and run the teach-and-repeat demo on the simulated robot
#   make test   set up .venv and run the whole test suite
# Both install vbnav with its test tools and the OAK extra (depthai), which the OAK tests use.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test bench venv clean docs

$(STAMP): pyproject.toml
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test,oak]'
	@touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(BIN)/vbnav demo --out out/demo

test: $(STAMP)
	$(BIN)/python -m pytest -q -ra --durations=15 -n auto --dist loadfile --no-loadscope-reorder

bench: $(STAMP)
	for b in benchmarks/*.py; do echo "== $$b"; $(BIN)/python $$b || exit 1; done

docs: $(STAMP)
	$(BIN)/vbnav config reference > docs/configuration.md

clean:
	rm -rf $(VENV) out build *.egg-info .pytest_cache
