# citytherm: make install | make test | make demo | make lint
# Every target installs what it needs on a fresh Debian machine (system packages need root).
VENV    ?= .venv
PYTHON  ?= python3
BIN     := $(VENV)/bin
STAMP   := $(VENV)/.citytherm-installed
SYSSTAMP:= $(VENV)/.citytherm-system

.PHONY: install system test lint unit integration demo bench clean

$(SYSSTAMP): .ci/system-deps.sh
	bash .ci/system-deps.sh
	@mkdir -p $(VENV) && touch $@

$(STAMP): pyproject.toml $(SYSSTAMP)
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e '.[dev]'
	touch $@

system: $(SYSSTAMP)

install: $(STAMP)

lint: $(STAMP)
	$(BIN)/ruff check .

test: $(STAMP)
	bash .ci/services-up.sh
	$(BIN)/ruff check .
	$(BIN)/pytest -q

unit: $(STAMP)
	$(BIN)/pytest -q tests/unit

integration: $(STAMP)
	bash .ci/services-up.sh
	$(BIN)/pytest -q tests/integration

demo: $(STAMP)
	$(BIN)/python -m services.demo --out demo-out

bench: $(STAMP)
	@for b in bench/*.py; do echo "== $$b"; $(BIN)/python $$b || exit 1; done

clean:
	rm -rf $(VENV) demo-out .pytest_cache .ruff_cache
