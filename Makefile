# Two entry points for a fresh Debian machine with Python 3.11 (see README):
#   make demo   set up .venv with the package alone and run the main job (scan of a built-in
#               scene on the virtual device); the examples/ scripts run in it too
#   make test   add the test extra (and Icarus Verilog, libusb) and run every test
# Both are idempotent: each install is redone only when pyproject.toml changes, and the
# test install (a superset) also satisfies the demo's.

PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
HASH   := $(shell cat pyproject.toml | cksum | cut -d' ' -f1)
BASE   := $(VENV)/.installed-base-$(HASH)
TESTED := $(VENV)/.installed-test-$(HASH)
SUDO   := $(shell [ "$$(id -u)" = 0 ] || echo sudo)

.PHONY: demo test lint bench sysdeps clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip

$(BASE): pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install -q -e .
	@rm -f $(VENV)/.installed-base-* && touch $@

$(TESTED): pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install -q -e '.[test]'
	@rm -f $(VENV)/.installed-* && touch $@ $(BASE)

# Debian packages the tests need: Icarus Verilog (co-simulation), libusb (Open3D imports it)
# and a software Vulkan driver (rerun's headless viewer renders the live view's screenshot).
sysdeps:
	@missing=""; command -v iverilog >/dev/null || missing="$$missing iverilog"; \
	{ /sbin/ldconfig -p 2>/dev/null || ldconfig -p; } | grep -q 'libusb-1.0.so.0' || missing="$$missing libusb-1.0-0"; \
	ls /usr/share/vulkan/icd.d/lvp_icd*.json >/dev/null 2>&1 || missing="$$missing mesa-vulkan-drivers"; \
	if [ -n "$$missing" ]; then $(SUDO) apt-get update -qq && \
		DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -qq $$missing >/dev/null; fi

demo: $(if $(wildcard $(TESTED)),$(TESTED),$(BASE))
	$(BIN)/cdma-lidar demo --out out/demo

test: $(TESTED) sysdeps
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -q

lint: $(TESTED)
	$(BIN)/ruff check .

bench: $(TESTED)
	$(BIN)/python -m bench

clean:
	rm -rf $(VENV) build sim_build out .pytest_cache .hypothesis
