# Two commands do all the set-up on a fresh machine: `make run ENV=...` and `make test`.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed-stamp

ENV    ?= lander
METHOD ?= shed
PRESET ?= auto
SEEDS  ?=
OUT    ?=
ARGS   ?=

.PHONY: setup run test bench demo clean

$(STAMP): pyproject.toml
	@$(PYTHON) -c 'import sys; assert sys.version_info >= (3, 11), "shed_jax needs Python >= 3.11, found " + sys.version.split()[0]'
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e ".[test]"
	@touch $(STAMP)

setup: $(STAMP)

run: $(STAMP)
	$(BIN)/python -m shed_jax run --env $(ENV) --method $(METHOD) --preset $(PRESET) $(if $(SEEDS),--seeds $(SEEDS),) $(if $(OUT),--out $(OUT),) $(ARGS)

demo: $(STAMP)
	$(BIN)/python -m shed_jax demo --env $(ENV) $(ARGS)

test: $(STAMP)
	$(BIN)/python -m pytest -q -n 2 --durations=15 $(ARGS)

bench: $(STAMP)
	$(BIN)/python -m experiments.bench $(ARGS)

clean:
	rm -rf $(VENV) .cache runs
