# Set-up, demo and tests on a fresh machine (Debian, Python 3.10+, root or sudo for one system library).
VENV ?= .venv
PY := $(VENV)/bin/python
SUDO := $(shell [ "$$(id -u)" = 0 ] || echo sudo)

.PHONY: setup demo test lint bench clean-venv

setup: $(VENV)/.installed

# Open3D needs Debian's libusb-1.0-0; torch is pinned to the CPU wheel provided on our machines
# (a bare torch requirement with no torch installed would pull several GB of CUDA packages).
# The diffusion extra (~35 MB of wheels, ~20 s) is installed so its tests run (tiny model, no weights).
$(VENV)/.installed: pyproject.toml setup.py
	@ldconfig -p | grep -q libusb-1.0.so.0 || ($(SUDO) apt-get update -qq && $(SUDO) apt-get install -y -qq libusb-1.0-0)
	@[ -x $(PY) ] || python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip setuptools wheel
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e ".[test,diffusion]"
	@touch $@

demo: setup
	$(VENV)/bin/sgpor-pipeline demo --out runs/demo
	$(VENV)/bin/sgpor-pipeline status runs/demo

lint: setup
	$(VENV)/bin/ruff check .

test: setup lint
	$(PY) -m pytest -q -n auto --maxprocesses 4

bench: setup
	$(PY) benchmarks/rasterizer.py

clean-venv:
	rm -rf $(VENV)
