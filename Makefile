# Two entry points do all the set-up on a fresh clone with Python >= 3.11 and pip:
#   make demo   - create .venv, install, render the demo data set and its contact sheet
#   make test   - the same set-up, then the whole test suite
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
TSTAMP := $(VENV)/.installed-test

.PHONY: demo test install bench clean

$(PY):
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip

# torch is pinned and installed first: on these machines torch==2.13.0 is a local CPU wheel,
# while an unpinned torch would pull a CUDA build of several GB.
$(STAMP): pyproject.toml setup.py | $(PY)
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e '.[train]'
	touch $(STAMP)

# The test suite also needs pytest and Ray (the distributed-executor tests start a local cluster).
$(TSTAMP): $(STAMP)
	$(PY) -m pip install -q -e '.[train,test,ray]'
	touch $(TSTAMP)

install: $(STAMP)

demo: $(STAMP)
	$(PY) -m dofsynth demo --out out

test: $(TSTAMP)
	$(PY) -m pytest -q -n 2

bench: $(TSTAMP)
	$(PY) benchmarks/render.py
	$(PY) benchmarks/generate.py
	$(PY) benchmarks/train.py

clean:
	rm -rf out build dist *.egg-info
