# Two commands for a new user: `make demo` and `make test` (see README).
# Both create .venv when it is missing and install the project into it.

PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
SHARED ?= ../shared/data
# pytest workers of make test (pytest-xdist; each test file runs whole on one worker)
JOBS   ?= 2

.PHONY: demo test test-vcan debs lint bench bank nn report clean install

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

# Re-install only when the project metadata changes.
$(VENV)/.installed: pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install --quiet -e .
	touch $@

$(VENV)/.installed-test: pyproject.toml $(VENV)/.installed
	$(BIN)/python -m pip install --quiet -e '.[test]'
	touch $@

install: $(VENV)/.installed

demo: $(VENV)/.installed
	$(BIN)/python -m captures.demo --data $(SHARED) $(DEMO_FLAGS)

# The whole suite; then the SocketCAN tests (pytest -m socketcan) on real vcan: they ran
# above where this kernel has vcan, else tools/vcanvm.py runs them in a QEMU VM booting
# Debian's stock kernel.  Where neither works they are reported as skipped, with the reason.
test: lint debs
	OPENBLAS_NUM_THREADS=1 $(BIN)/python -m pytest -n $(JOBS) --dist loadfile
	OPENBLAS_NUM_THREADS=1 $(BIN)/python tools/vcanvm.py pytest --if-needed

# ruff, then the import rules of docs/architecture.md (import-linter; pyproject.toml has the
# contracts, tools/import_contracts.py the one about cycles between files).
lint: $(VENV)/.installed-test
	$(BIN)/ruff check src tests bench tools
	PYTHONPATH=tools $(BIN)/lint-imports --no-cache

# Only the SocketCAN tests, on this kernel's vcan or in the VM.
test-vcan: $(VENV)/.installed-test debs
	OPENBLAS_NUM_THREADS=1 $(BIN)/python tools/vcanvm.py pytest

# Debian packages the tests need: can-utils (the independent CAN peer: candump, canplayer,
# isotprecv), iproute2 (vcan), qemu-system-x86, busybox-static and kmod (the VM that gives
# a kernel without SocketCAN one), tshark and openssl (the independent checks of the IEEE
# 1609.2 frames: Wireshark's dissectors, OpenSSL's ECDSA), chromium and fonts-dejavu-core
# (the live view's tests drive the real page in Debian's headless Chromium through
# Playwright; no browser download), gpsd and gpsd-clients (the independent GNSS peer: gpsd
# reads the RVE's NMEA from a pty, gpspipe reports its fixes).  Installed when missing and we are root; otherwise the
# tests say what is missing.  The apt-get line below names the same packages.
DEBS = can-utils iproute2 qemu-system-x86 busybox-static kmod tshark openssl chromium fonts-dejavu-core gpsd gpsd-clients
debs:
	@missing=$$(for p in $(DEBS); do dpkg -s $$p >/dev/null 2>&1 || echo $$p; done); \
	if [ -z "$$missing" ]; then exit 0; fi; \
	if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	  echo "debs: installing" $$missing; \
	  apt-get update -q >/dev/null; \
	  DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends can-utils iproute2 qemu-system-x86 busybox-static kmod tshark openssl chromium fonts-dejavu-core gpsd gpsd-clients >/dev/null; \
	else echo "debs: missing" $$missing "(not root, or no apt-get): the tests that need them say so"; fi

bench: $(VENV)/.installed
	$(BIN)/python bench/codec.py

# The paper's experiments on the shared real data as one report (out/report/report.html),
# published as docs/results.md with its figures in docs/results/.
report: $(VENV)/.installed-test
	OPENBLAS_NUM_THREADS=1 $(BIN)/captures report --data $(SHARED) --workers 2 \
	  --live 50@10,90@10 --out out/report --results docs/results.md

# The learned models' training trips (the OpenACC dynamic runs and the NGSIM pairs) and the
# trips held out of training (the OpenACC handling runs), shared by `bank` and `nn`.
TRAIN_TRIPS = \
	  --dataset $(SHARED)/openacc-zalazone/short_setting_dynamic_part1.csv \
	  --dataset $(SHARED)/openacc-zalazone/short_setting_dynamic_part22.csv \
	  --dataset $(SHARED)/openacc-zalazone/long_setting_dynamic_part16.csv \
	  --dataset $(SHARED)/openacc-zalazone/mixed_dynamic_part7.csv \
	  --dataset ngsim:$(SHARED)/ngsim-i80-pairs \
	  --holdout $(SHARED)/openacc-zalazone/short_setting_handling_part36.csv \
	  --holdout $(SHARED)/openacc-zalazone/no_ACC_handling_part40.csv

# Re-create the default HGP kernel bank shipped in the package from ../shared/data.
bank: $(VENV)/.installed
	$(BIN)/captures train-bank $(TRAIN_TRIPS) --out src/catc/predict/default_bank.json

# Re-create the neural baselines' weights shipped in the package (ae, ae-d, lstm, lstm-d)
# from ../shared/data: the HGP bank's training trips and hold-outs (about an hour on 2 cores).
nn: $(VENV)/.installed-test
	$(BIN)/captures train-nn $(TRAIN_TRIPS) --out src/catc/predict/nn

clean:
	rm -rf $(VENV) build *.egg-info src/*.egg-info .pytest_cache
