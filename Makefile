# `make demo` and `make test` (the README's two commands), `make test-all` (what CI runs), `make docs`
# and `make lint`. Each creates .venv when missing and installs what it needs, saying so.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
PIP    := $(PY) -m pip -q --disable-pip-version-check

.PHONY: test test-all lint docs demo bench clean syslibs

$(PY):
	$(PYTHON) -m venv $(VENV)

# Re-install when the dependency list (pyproject.toml, the extras named here) changes.
# torch first, pinned: its CPU build (a bare "torch" requirement would pull a multi-GB CUDA one).
$(VENV)/.installed: pyproject.toml setup.py Makefile | $(PY)
	@echo "installing into $(VENV) (first time: a few minutes): torch (CPU build)"
	$(PIP) install torch==2.13.0
	@echo "installing ovamos and its extras (dev, docs, sim, perception, camera, ros2)"
	$(PIP) install -e '.[dev,docs,sim,perception,camera,ros2,cluster]'
	touch $@

# System libraries from Debian/Ubuntu packages, installed when missing (with sudo
# when not root and sudo exists): the simulator renders headless through EGL
# (Mesa's software rasteriser when there is no GPU), and pyrealsense2 (the camera
# service's RealSense backend) loads libusb-1.0; the operator page's tests drive
# Debian's chromium through chromium-driver (selenium).
SUDO := $(shell [ "$$(id -u)" -ne 0 ] && command -v sudo >/dev/null && echo sudo)
syslibs:
	@libs="$$( { ldconfig -p 2>/dev/null || /sbin/ldconfig -p; } )"; pkgs=""; \
	echo "$$libs" | grep -q libEGL.so.1 || pkgs="$$pkgs libegl1 libgl1-mesa-dri libgles2"; \
	echo "$$libs" | grep -q libusb-1.0.so.0 || pkgs="$$pkgs libusb-1.0-0"; \
	command -v chromium >/dev/null || pkgs="$$pkgs chromium"; \
	command -v chromedriver >/dev/null || pkgs="$$pkgs chromium-driver"; \
	if [ -n "$$pkgs" ]; then \
	  echo "missing system packages: installing$$pkgs"; \
	  $(SUDO) apt-get update && \
	  $(SUDO) env DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends $$pkgs; \
	fi

# Two tiers. `make test`: the fast tier (cores, adapters on the fake bus and in-process Zenoh, the
# codec, one end-to-end demo): every test not marked `system`, plus the `demo` one. `make test-all`:
# lint, every test, and tests/ros2 -- these load DDS, so they run in a loopback-only network namespace
# of their own (shared/dds.py), which `unshare` makes for root; elsewhere they are skipped, saying so.
test: $(VENV)/.installed syslibs
	$(PY) -m pytest -q -m "not system or demo"

test-all: $(VENV)/.installed syslibs lint
	$(PY) -m pytest -q --durations=25
	@if unshare --net --mount true 2>/dev/null; then $(PY) -m ovamos.shared.dds -- $(PY) -m pytest -q --durations=10 tests/ros2; \
	else echo "tests/ros2 skipped: unshare --net --mount needs root (they load DDS)"; fi

# ruff, the import contracts (import-linter) and mypy on the cores: tools/lint.py, configured in pyproject.toml
lint: $(VENV)/.installed
	$(PY) tools/lint.py

# The documentation site into site/ (offline); the generated references are rewritten first.
docs: $(VENV)/.installed
	$(PY) tools/gen_reference.py
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict

demo: $(VENV)/.installed syslibs
	$(VENV)/bin/ovamos demo

bench: $(VENV)/.installed syslibs
	$(VENV)/bin/ovamos bench transport
	$(VENV)/bin/ovamos bench transport --tls
	$(VENV)/bin/ovamos bench sim
	$(VENV)/bin/ovamos bench mapping
	$(VENV)/bin/ovamos bench planner
	$(VENV)/bin/ovamos bench perception
	$(VENV)/bin/ovamos bench camera

clean:
	rm -rf $(VENV) .pytest_cache .hypothesis site build
