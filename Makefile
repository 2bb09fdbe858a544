# `make demo` and `make test` (the README's two commands), `make test-all` (what CI runs), `make docs`
# and `make lint`. Each creates .venv when missing and installs what it needs, saying so.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
PIP    := $(PY) -m pip -q --disable-pip-version-check

.PHONY: test test-all lint docs demo bench clean syslibs

$(PY):
	$(PYTHON) -m venv $(VENV)

# The extras `make test` installs, and the README's by-hand install line (tests/test_install.py
# holds the two together): everything, for the tests, the docs and the benchmarks.
EXTRAS := dev,docs,sim,perception,camera,ros2,cluster,slam
# torch, pinned and installed first: from PyPI, Linux's build is the CUDA one (what a GPU laptop
# wants); TORCH_INDEX=https://download.pytorch.org/whl/cpu takes PyTorch's CPU-only build (a CI box,
# a robot), as PyTorch's own instructions give it. A bare "torch" requirement in the extras would
# pull the newest CUDA build instead. (Here a local wheel folder serves the CPU build for the line as it is.)
TORCH       ?= torch==2.13.0
TORCH_INDEX ?=

# Re-install when the dependency list (pyproject.toml, the extras named here) changes.
$(VENV)/.installed: pyproject.toml setup.py Makefile | $(PY)
	@echo "installing into $(VENV) (first time: a few minutes): $(TORCH)$(if $(TORCH_INDEX), from $(TORCH_INDEX))"
	$(PIP) install $(TORCH) $(if $(TORCH_INDEX),--index-url $(TORCH_INDEX))
	@echo "installing ovamos and its extras ($(EXTRAS))"
	$(PIP) install -e '.[$(EXTRAS)]'
	touch $@ $(VENV)/.installed-demo

# The demo needs the simulator and nothing else: no torch (its perception is the simulated one),
# no browser, no ROS.
$(VENV)/.installed-demo: pyproject.toml setup.py Makefile | $(PY)
	@echo "installing ovamos and the simulator into $(VENV) (first time: a minute or two)"
	$(PIP) install -e '.[sim]'
	touch $@

# System libraries from Debian/Ubuntu packages, installed when missing: tools/syslibs.sh says which.
syslibs:
	@tools/syslibs.sh test

# Two tiers. `make test`: the fast tier (cores, adapters on the fake bus and in-process Zenoh, the
# codec, one end-to-end demo): every test not marked `system`, plus the `demo` one. `make test-all`:
# lint, every test, and tests/ros2 -- these load DDS, so they run in a loopback-only network namespace
# of their own (shared/dds.py), which `unshare` makes for root; elsewhere they are skipped, saying so.
test: $(VENV)/.installed syslibs
	$(PY) -m pytest -q -m "not system or demo"

# test-all: the tests on WORKERS processes (most of their time is waiting on the processes they start),
# then the `serial` ones alone (real-time devices and deadlines, which a loaded machine would miss).
WORKERS ?= 3
test-all: $(VENV)/.installed syslibs lint
	$(PY) -m pytest -q -n $(WORKERS) --dist worksteal -m "not serial" --durations=25
	$(PY) -m pytest -q -m serial --durations=5
	@if unshare --net --mount true 2>/dev/null; then $(PY) -m ovamos.shared.dds -- $(PY) -m pytest -q -n 2 --durations=10 tests/ros2; \
	else echo "tests/ros2 skipped: unshare --net --mount needs root (they load DDS)"; fi

# ruff, the import contracts (import-linter) and mypy on the cores: tools/lint.py, configured in pyproject.toml
lint: $(VENV)/.installed
	$(PY) tools/lint.py

# The documentation site into site/ (offline); the generated references are rewritten first.
docs: $(VENV)/.installed
	$(PY) tools/gen_reference.py
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict

demo: $(VENV)/.installed-demo
	@tools/syslibs.sh demo
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
