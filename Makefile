# Two entry points for a fresh machine: `make demo` and `make test`. Both install what
# they need (Debian packages, a Python venv) before building.

VENV        := .venv
PYTHON      := $(VENV)/bin/python
CARGO       ?= cargo
WHEEL_DIR   := dist
CLI         := target/release/crepuscular
export VIRTUAL_ENV := $(abspath $(VENV))
export PATH := $(VIRTUAL_ENV)/bin:$(PATH)

.PHONY: demo test system-deps build wheel addon usd-package rust-test python-test lint bench clean

demo: build $(VENV)/.test-deps
	$(CLI) demo --out-dir out/demo
	$(PYTHON) blender_addon/build_extension.py $(WHEEL_DIR) out/addon
	$(PYTHON) examples/blender_demo.py out/demo/blender

test: system-deps $(VENV)/.test-deps lint rust-test wheel addon python-test

system-deps:
	@.ci/system-deps

$(VENV)/.build-deps: tests/requirements-build.txt
	python3 -m venv $(VENV)
	$(PYTHON) -m pip install --quiet --upgrade pip
	$(PYTHON) -m pip install --quiet -r tests/requirements-build.txt
	touch $@

$(VENV)/.test-deps: $(VENV)/.build-deps tests/requirements-test.txt
	$(PYTHON) -m pip install --quiet -r tests/requirements-test.txt
	touch $@

build: $(VENV)/.build-deps
	$(CARGO) build --release -p crepuscular
	$(MAKE) wheel

wheel: $(VENV)/.build-deps
	rm -rf $(WHEEL_DIR)
	maturin build --release --quiet -m core/python/Cargo.toml -o $(WHEEL_DIR)
	$(PYTHON) -m pip install --quiet --force-reinstall --no-deps $(WHEEL_DIR)/crepuscular-*.whl

# The USD step (crepuscular_usd and the crepuscular-usd command), editable so that tests
# and the console script run the sources; its dependencies come from the test requirements.
usd-package: $(VENV)/.test-deps
	$(PYTHON) -m pip install --quiet --no-deps -e usd

lint: $(VENV)/.test-deps
	$(CARGO) fmt --all --check
	$(CARGO) clippy --workspace --all-targets --release -- -D warnings
	RUSTDOCFLAGS="-D warnings" $(CARGO) doc --workspace --no-deps
	ruff check core/python tests examples usd blender_addon
	ruff format --check core/python tests examples usd blender_addon

# The Blender extension zip (add-on sources, manifest and the wheel above) in out/addon/.
addon: wheel
	$(PYTHON) blender_addon/build_extension.py $(WHEEL_DIR) out/addon

rust-test:
	$(CARGO) test -p crepuscular --release

python-test: $(VENV)/.test-deps usd-package
	$(PYTHON) -m pytest tests -q

bench: build
	$(CLI) bench

clean:
	rm -rf target $(WHEEL_DIR) out
