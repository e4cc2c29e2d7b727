# Two entry points do all the set-up on a fresh clone with Python >= 3.11 and pip:
#   make demo   - create .venv, install, render the demo data set and its contact sheet
#   make test   - the same set-up, then the whole test suite
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
TSTAMP := $(VENV)/.installed-test

.PHONY: demo test install bench clean browser

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

# The QA page's browser test drives Debian's Chromium and ChromeDriver (/usr/bin/chromium,
# /usr/bin/chromedriver); they are installed here when missing and the machine allows it (root
# with apt-get, as on CI). Elsewhere that test skips, saying why (and fails where CI is set).
browser:
	@if ! command -v chromium >/dev/null || ! command -v chromedriver >/dev/null; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    echo "installing Debian's chromium and chromium-driver for the QA page's browser test"; \
	    export DEBIAN_FRONTEND=noninteractive; \
	    apt-get install -y -q chromium chromium-driver >/dev/null 2>&1 || \
	      { apt-get update -q >/dev/null && apt-get install -y -q chromium chromium-driver >/dev/null; }; \
	  else echo "chromium/chromedriver not installed: the QA page's browser test will skip"; fi; \
	fi

test: $(TSTAMP) browser
	$(PY) -m pytest -q -n 2

bench: $(TSTAMP)
	$(PY) benchmarks/render.py
	$(PY) benchmarks/generate.py
	$(PY) benchmarks/train.py

clean:
	rm -rf out build dist *.egg-info
