# Two entry points for a fresh Debian machine with Python 3.11 (see README):
#   make demo   set up .venv and run the main job (scan of a built-in scene on the virtual device)
#   make test   set up .venv (and Icarus Verilog, libusb) and run every test
# Both are idempotent: the venv is rebuilt only when pyproject.toml changes.

PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed-$(shell cat pyproject.toml | cksum | cut -d' ' -f1)
SUDO   := $(shell [ "$$(id -u)" = 0 ] || echo sudo)

.PHONY: demo test lint bench sysdeps clean

$(STAMP): pyproject.toml
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[test]'
	@rm -f $(VENV)/.installed-* && touch $@

# Debian packages the tests need: Icarus Verilog (co-simulation) and libusb (Open3D imports it).
sysdeps:
	@missing=""; command -v iverilog >/dev/null || missing="$$missing iverilog"; \
	{ /sbin/ldconfig -p 2>/dev/null || ldconfig -p; } | grep -q 'libusb-1.0.so.0' || missing="$$missing libusb-1.0-0"; \
	if [ -n "$$missing" ]; then $(SUDO) apt-get update -qq && \
		DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -qq $$missing >/dev/null; fi

demo: $(STAMP)
	$(BIN)/cdma-lidar demo --out out/demo

test: $(STAMP) sysdeps
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -q

lint: $(STAMP)
	$(BIN)/ruff check .

bench: $(STAMP)
	$(BIN)/python -m bench

clean:
	rm -rf $(VENV) build sim_build out .pytest_cache .hypothesis
