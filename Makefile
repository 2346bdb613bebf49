# Two commands do all the set-up on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3.11
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
APT_PACKAGES := libosmesa6 libgl1 libegl1 libxkbcommon0 libfontconfig1 libdbus-1-3
export QT_QPA_PLATFORM ?= offscreen
export MPLBACKEND ?= Agg

.PHONY: demo test bench venv system-deps clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet torch==2.13.0
	$(PY) -m pip install --quiet -e '.[test,gui]'
	touch $(STAMP)

venv: system-deps $(STAMP)

# Debian packages the offscreen Qt + VTK tests need; installed when missing and we are root.
system-deps:
	@missing=""; for p in $(APT_PACKAGES); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	if [ -n "$$missing" ]; then \
	  if [ "$$(id -u)" = "0" ]; then apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$missing >/dev/null; \
	  else echo "missing Debian packages; run: sudo apt-get install -y$$missing"; fi; \
	fi

demo: venv
	$(VENV)/bin/fevar-planner demo --out demo_out

test: venv
	$(PY) -m pytest -q Testing

bench: venv
	$(PY) Testing/benchmarks/run_all.py --out Testing/benchmarks/results

clean:
	rm -rf $(VENV) demo_out Testing/benchmarks/results
