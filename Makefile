# markcal: `make demo` and `make test` work on a fresh machine.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
DEMO   := demo_out

.PHONY: demo test bench sysdeps browser mutants clean

# Open3D needs the system library libusb-1.0 (import open3d fails without it).
sysdeps:
	@if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then \
	  if [ "$$(id -u)" = "0" ] && command -v apt-get >/dev/null; then \
	    echo "installing libusb-1.0-0 with apt-get (needed by Open3D)"; \
	    (apt-get install -y -q libusb-1.0-0 >/dev/null 2>&1 || \
	     (apt-get update -q >/dev/null && apt-get install -y -q libusb-1.0-0 >/dev/null)) || \
	     { echo "apt-get could not install libusb-1.0-0; install it and re-run"; exit 1; }; \
	  else \
	    echo "markcal needs the system library libusb-1.0 for Open3D: install it (e.g. sudo apt-get install libusb-1.0-0) and re-run"; exit 1; \
	  fi; \
	fi

# The browser test (tests/test_browser.py) drives Debian's chromium; a test never installs packages,
# so the test target does it here. In CI (CI=true) the browser test fails when chromium is missing.
browser:
	@if ! command -v chromium >/dev/null 2>&1 && [ ! -x /usr/bin/chromium ]; then \
	  if [ "$$(id -u)" = "0" ] && command -v apt-get >/dev/null; then \
	    echo "installing chromium with apt-get (needed by tests/test_browser.py)"; \
	    (apt-get install -y -q chromium >/dev/null 2>&1 || \
	     (apt-get update -q >/dev/null && apt-get install -y -q chromium >/dev/null)) || \
	     { echo "apt-get could not install chromium; install it and re-run (the browser test needs it)"; exit 1; }; \
	  else \
	    echo "tests/test_browser.py needs Debian's chromium: install it (e.g. sudo apt-get install chromium);"; \
	    echo "without it the browser test is skipped here and fails in CI"; \
	  fi; \
	fi

$(STAMP): pyproject.toml | sysdeps
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[test]'
	@touch $(STAMP)

# A small mixed batch (plates, self-calibration sessions, servo traces, an AFM map, a micrograph and
# one broken file on purpose) through `markcal batch`. Exit status 3 means "some inputs failed to
# process", which the broken file causes by design; any other failure stops make.
demo: sysdeps $(STAMP)
	rm -rf $(DEMO)
	$(VENV)/bin/markcal render batch --seed 7 --out $(DEMO)/inputs --scans 3 --sessions 2 --traces 3 --maps 1 --micrographs 1 --broken 1
	$(VENV)/bin/markcal batch $(DEMO)/inputs --out $(DEMO)/batch --workers 2; rc=$$?; \
	  if [ $$rc -ne 0 ] && [ $$rc -ne 3 ]; then exit $$rc; fi
	@echo ""
	@echo "batch index: $$(pwd)/$(DEMO)/batch/index.html"

# The suite runs on two workers (pytest-xdist): about half the wall time on a 2-core machine.
test: sysdeps browser $(STAMP)
	$(PY) -m pytest -n 2

# Mutation score of the measurement stages: each mutant runs only its stage's fast tests with -x
# (benchmarks/mutants.py; a few minutes on 2 cores). Prints the score, the survivors and which
# survivors are equivalent.
mutants: sysdeps $(STAMP)
	$(PY) benchmarks/mutants.py

bench: sysdeps $(STAMP)
	$(PY) -m pip install -q -e '.[test,bench]'
	$(PY) benchmarks/bench_scan.py
	$(PY) benchmarks/accuracy_sweep.py
	$(PY) benchmarks/bench_selfcal.py
	$(PY) benchmarks/bench_export.py
	$(PY) benchmarks/bench_servo.py
	$(PY) benchmarks/bench_path.py
	$(PY) benchmarks/bench_pmcal.py
	$(PY) benchmarks/bench_indents.py
	$(PY) benchmarks/bench_batch.py

clean:
	rm -rf $(VENV) $(DEMO) bench_out .pytest_cache
