# Two commands on a fresh machine with Python 3.11:  make run   and   make test
PYTHON ?= python3
VENV   ?= .venv
BIN     = $(VENV)/bin

.PHONY: setup setup-test run test clean

# The core (what the main job needs), and on top of it what the tests need: each command installs
# only what it uses.
setup: $(VENV)/.installed-core

setup-test: $(VENV)/.installed-test

$(VENV)/.installed-core: pyproject.toml
	@$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else "Python >= 3.11 is required (set PYTHON=...)")'
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e .
	touch $@

$(VENV)/.installed-test: $(VENV)/.installed-core
	$(BIN)/python -m pip install -q -e ".[dev,atari,minatar,popgym,ray,wandb]"
	touch $@

# Train ESCORT-RL's default job (Light-Dark 10D) and evaluate it; results in
# outputs/lightdark10d/escort_train-ppo-seed0/.
run: setup
	$(BIN)/escort-rl run $(ARGS)

test: setup-test
	$(BIN)/python -m pytest -q $(PYTEST_ARGS)

clean:
	rm -rf $(VENV) outputs .pytest_cache
