# markcal: `make demo` and `make test` work on a fresh machine.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
DEMO   := demo_out

.PHONY: demo test bench sysdeps clean

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

$(STAMP): pyproject.toml | sysdeps
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[test]'
	@touch $(STAMP)

demo: sysdeps $(STAMP)
	$(VENV)/bin/markcal render scan --seed 7 --out $(DEMO)/plate
	$(VENV)/bin/markcal scan $(DEMO)/plate/cloud.ply --plate $(DEMO)/plate/plate.toml --out $(DEMO)/calibration
	$(VENV)/bin/markcal render scan --seed 8 --machine-seed 7 --correction $(DEMO)/calibration/correction_grid.csv --out $(DEMO)/validation_plate
	$(VENV)/bin/markcal scan $(DEMO)/validation_plate/cloud.ply --plate $(DEMO)/validation_plate/plate.toml --out $(DEMO)/validation --validation
	@echo ""
	@echo "calibration report: $$(pwd)/$(DEMO)/calibration/report.html"
	@echo "validation report:  $$(pwd)/$(DEMO)/validation/report.html"

test: sysdeps $(STAMP)
	$(PY) -m pytest

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

clean:
	rm -rf $(VENV) $(DEMO) bench_out .pytest_cache
