# Set-up, demo and tests on a fresh Debian machine. Each target does only the
# set-up that is missing: apt packages, the virtual environment, the editable build.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
APT_PACKAGES := libopengv-dev libeigen3-dev cmake g++ ninja-build python3-venv colmap time
STAMPS := $(VENV)/.stamps

.PHONY: install demo test benchmark clean

install: $(STAMPS)/installed

# Checked again when this file changes (a package added); the venv does not depend on it.
$(STAMPS)/apt: Makefile
	@missing=$$(for p in $(APT_PACKAGES); do dpkg -s $$p >/dev/null 2>&1 || echo $$p; done); \
	if [ -n "$$missing" ]; then \
	  if [ "$$(id -u)" = 0 ]; then SUDO=; elif command -v sudo >/dev/null; then SUDO=sudo; \
	  else echo "error: need root or sudo to install Debian packages: $$missing" >&2; exit 1; fi; \
	  echo "Installing Debian packages: $$missing"; \
	  $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq $$missing; \
	fi
	@mkdir -p $(STAMPS) && touch $@

$(STAMPS)/venv: requirements-build.txt | $(STAMPS)/apt
	@[ -x $(PY) ] || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -r requirements-build.txt
	@touch $@

# The editable install lists the Python modules: again when a package folder gains or
# loses one (its folder's time changes).
$(STAMPS)/installed: $(STAMPS)/venv pyproject.toml $(shell find cpp -type f) \
		$(shell find colmap_ext solvers -type d -not -name __pycache__)
	$(PY) -m pip install -q --no-build-isolation -e '.[test]'
	@touch $@

demo: install
	$(VENV)/bin/colmap-ext demo --output_path demo_output --overwrite

test: install
	$(PY) -m pytest -q

benchmark: install
	$(PY) benchmarks/solvers.py

clean:
	rm -rf build $(VENV) demo_output
