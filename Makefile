# The README's two commands. Both create .venv when missing and install what they need.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
PIP    := $(PY) -m pip -q --disable-pip-version-check

.PHONY: test demo bench clean

$(PY):
	$(PYTHON) -m venv $(VENV)

# Re-install when the dependency list changes.
$(VENV)/.installed: pyproject.toml | $(PY)
	$(PIP) install -e '.[dev]'
	touch $@

test: $(VENV)/.installed
	$(PY) -m pytest -q

demo: $(VENV)/.installed
	$(VENV)/bin/ovamos demo

bench: $(VENV)/.installed
	$(VENV)/bin/ovamos bench transport

clean:
	rm -rf $(VENV) .pytest_cache .hypothesis
