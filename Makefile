# Two commands do all the set-up on a fresh machine: `make run ENV=...` and `make test`.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
# JAX build: auto (nvidia-smi picks cpu, cuda12 or cuda13; shed_jax/_backend_select.py says why) or
# one of those three. The stamp names the build, so a different choice reinstalls.
JAX_BACKEND ?= auto
ifneq ($(MAKECMDGOALS),clean)
BACKEND := $(shell $(PYTHON) shed_jax/_backend_select.py --name "$(JAX_BACKEND)" 2>&1)
ifneq ($(words $(BACKEND)) $(filter $(BACKEND),cpu cuda12 cuda13),1 $(BACKEND))
$(error $(or $(BACKEND),$(PYTHON) shed_jax/_backend_select.py printed nothing))
endif
endif
comma  := ,
STAMP  := $(VENV)/.installed-$(BACKEND)
EXTRAS := test$(if $(filter cuda%,$(BACKEND)),$(comma)$(BACKEND),)

ENV    ?= lander
METHOD ?= shed
PRESET ?= auto
SEEDS  ?=
OUT    ?=
ARGS   ?=

.PHONY: setup run test bench demo clean

$(STAMP): pyproject.toml
	@$(PYTHON) -c 'import sys; assert sys.version_info >= (3, 11), "shed_jax needs Python >= 3.11, found " + sys.version.split()[0]'
	@$(PYTHON) shed_jax/_backend_select.py "$(JAX_BACKEND)"
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	@rm -f $(VENV)/.installed-*
	$(BIN)/python -m pip install -q --upgrade pip
	@stale="$$($(BIN)/python shed_jax/_backend_select.py --stale $(BACKEND))"; \
	if [ -n "$$stale" ]; then echo "removing JAX plugins of another build: $$stale"; $(BIN)/python -m pip uninstall -q -y $$stale; fi
	$(BIN)/python -m pip install -q -e ".[$(EXTRAS)]"
	@touch $(STAMP)

setup: $(STAMP)

run: $(STAMP)
	$(BIN)/python -m shed_jax run --env $(ENV) --method $(METHOD) --preset $(PRESET) $(if $(SEEDS),--seeds $(SEEDS),) $(if $(OUT),--out $(OUT),) $(ARGS)

demo: $(STAMP)
	$(BIN)/python -m shed_jax demo --env $(ENV) $(ARGS)

test: $(STAMP)
	$(BIN)/python -m pytest -q -n 2 --dist worksteal --durations=15 $(ARGS)

bench: $(STAMP)
	$(BIN)/python -m experiments.bench $(ARGS)

clean:
	rm -rf $(VENV) .cache runs
