# The README's two commands. Both create .venv when missing and install what they need.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
PIP    := $(PY) -m pip -q --disable-pip-version-check

.PHONY: test demo bench clean egl

$(PY):
	$(PYTHON) -m venv $(VENV)

# Re-install when the dependency list (pyproject.toml, the extras named here) changes.
# torch first, pinned: its CPU build (a bare "torch" requirement would pull a multi-GB CUDA one).
$(VENV)/.installed: pyproject.toml Makefile | $(PY)
	$(PIP) install torch==2.13.0
	$(PIP) install -e '.[dev,sim,perception]'
	touch $@

# The simulator renders headless through EGL (Mesa's software rasteriser when
# there is no GPU). On a fresh Debian/Ubuntu machine those system libraries are
# missing: install them, with sudo when not root and sudo exists.
SUDO := $(shell [ "$$(id -u)" -ne 0 ] && command -v sudo >/dev/null && echo sudo)
egl:
	@if ! { ldconfig -p 2>/dev/null || /sbin/ldconfig -p; } | grep -q libEGL.so.1; then \
	  echo "libEGL.so.1 not found: installing the EGL/Mesa libraries"; \
	  $(SUDO) apt-get update && \
	  $(SUDO) env DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends \
	    libegl1 libgl1-mesa-dri libgles2; \
	fi

test: $(VENV)/.installed egl
	$(PY) -m pytest -q

demo: $(VENV)/.installed
	$(VENV)/bin/ovamos demo

bench: $(VENV)/.installed egl
	$(VENV)/bin/ovamos bench transport
	$(VENV)/bin/ovamos bench sim
	$(VENV)/bin/ovamos bench mapping
	$(VENV)/bin/ovamos bench planner
	$(VENV)/bin/ovamos bench perception

clean:
	rm -rf $(VENV) .pytest_cache .hypothesis
