# citytherm: make install | make test | make demo | make lint
# Every target installs what it needs on a fresh Debian machine (system packages need root).
VENV    ?= .venv
PYTHON  ?= python3
BIN     := $(VENV)/bin
STAMP   := $(VENV)/.citytherm-installed
SYSSTAMP:= $(VENV)/.citytherm-system
VALIDATOR := tools/gltf-validator/node_modules/.package-lock.json
VIEWER  := services/api/viewer/vendor/three/build/three.module.js

.PHONY: install system test lint unit integration demo bench clean viewer

$(SYSSTAMP): .ci/system-deps.sh
	bash .ci/system-deps.sh
	@mkdir -p $(VENV) && touch $@

# setup.py compiles the import's C extensions (pip install -e builds them in place)
$(STAMP): pyproject.toml setup.py db/citygml/_walk.pyx db/_fmt.pyx db/_ryu/pyrepr64.h $(SYSSTAMP)
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e '.[dev]'
	touch $@

$(VALIDATOR): tools/gltf-validator/package-lock.json $(SYSSTAMP)
	cd tools/gltf-validator && npm ci --no-audit --no-fund

$(VIEWER): tools/viewer/package-lock.json tools/viewer/vendor.mjs $(SYSSTAMP)
	cd tools/viewer && npm ci --no-audit --no-fund && node vendor.mjs

viewer: $(VIEWER)

system: $(SYSSTAMP)

install: $(STAMP)

lint: $(STAMP)
	$(BIN)/ruff check .

test: $(STAMP) $(VALIDATOR) $(VIEWER)
	bash .ci/services-up.sh
	$(BIN)/ruff check .
	$(BIN)/pytest -q

unit: $(STAMP) $(VALIDATOR)
	$(BIN)/pytest -q tests/unit

integration: $(STAMP) $(VALIDATOR) $(VIEWER)
	bash .ci/services-up.sh
	$(BIN)/pytest -q tests/integration

demo: $(STAMP)
	$(BIN)/python -m services.demo --out demo-out

bench: $(STAMP)
	@for b in bench/*.py; do echo "== $$b"; $(BIN)/python $$b || exit 1; done

clean:
	rm -rf $(VENV) demo-out .pytest_cache .ruff_cache
