# roadsurf: two commands on a fresh clone, `make demo` and `make test`.
SHELL := /bin/bash
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
DEMO_OUT ?= out/demo

.PHONY: demo test lint typecheck format sysdeps venv clean sample browser-deps screenshots

# open3d 0.20 links libusb-1.0; install it with apt-get when the loader cannot find it.
sysdeps:
	@if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then \
	  echo "Installing system library libusb-1.0-0 (needed by open3d)"; \
	  if [ "$$(id -u)" = "0" ]; then apt-get update -qq && apt-get install -y -qq libusb-1.0-0; \
	  else sudo apt-get update -qq && sudo apt-get install -y -qq libusb-1.0-0; fi; \
	fi

# Headless Chromium for the viewer's browser checks (report.html, --serve); tests skip those
# checks with a message when it is missing. Debian/Ubuntu package name: chromium.
browser-deps:
	@if ! command -v chromium >/dev/null 2>&1 && ! command -v chromium-browser >/dev/null 2>&1; then \
	  echo "Installing chromium (headless browser checks of the viewer)"; \
	  if [ "$$(id -u)" = "0" ]; then apt-get update -qq && apt-get install -y -qq chromium; \
	  else sudo apt-get update -qq && sudo apt-get install -y -qq chromium; fi; \
	fi

# Large wheels (open3d is 400 MB) can lose their connection half way: pip resumes a partial
# download where it supports it (pip >= 25.1), and the whole install is tried 3 times.
define PIP_INSTALL
	@resume=$$($(BIN)/python -m pip install --help 2>/dev/null | grep -q -- '--resume-retries' && echo '--resume-retries=20'); \
	for i in 1 2 3; do \
	  $(BIN)/python -m pip install -q --retries 10 --timeout 60 $$resume $(1) && break; \
	  if [ $$i = 3 ]; then echo "pip install $(1) failed 3 times: check the network (PyPI) and run make again" >&2; exit 1; fi; \
	  echo "pip install $(1) failed (attempt $$i of 3); retrying in 15 s" >&2; sleep 15; \
	done
endef

$(STAMP): pyproject.toml
	@$(MAKE) --no-print-directory sysdeps
	@test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(call PIP_INSTALL,--upgrade pip)
	# torch first and exactly pinned, so no resolver step can pick a CUDA build.
	$(call PIP_INSTALL,torch==2.13.0)
	$(call PIP_INSTALL,-e '.[dev]')
	@touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	@start=$$(date +%s); \
	$(BIN)/roadsurf run data_samples/drive --out $(DEMO_OUT) && \
	$(BIN)/roadsurf view $(DEMO_OUT) --save $(DEMO_OUT)/run.rrd && \
	$(BIN)/roadsurf report $(DEMO_OUT) && \
	echo "Demo finished in $$(( $$(date +%s) - start )) s. Outputs in $(DEMO_OUT)/" && \
	ls -1 $(DEMO_OUT) | sed 's/^/  /' && \
	echo "Report:    $(DEMO_OUT)/report.html" && \
	echo "Recording: $(DEMO_OUT)/run.rrd"

# The tests include real headless-Chromium checks of the HTML report, so the test set-up
# installs Chromium from Debian (browser-deps) before running them.
test: $(STAMP) browser-deps
	$(BIN)/python -m pytest -q tests

# Benchmarks live outside the package: `make bench-NAME ARGS="..."` runs
# `python -m benchmarks.NAME ARGS` and writes benchmarks/results/NAME.json (docs/benchmarks.md).
bench-%: $(STAMP)
	$(BIN)/python -m benchmarks.$* $(ARGS)

lint: $(STAMP)
	$(BIN)/ruff check . && $(BIN)/ruff format --check . && $(MAKE) --no-print-directory typecheck

# Type check of the public API: core, io, pipeline and cli (mypy; settings in pyproject.toml).
typecheck: $(STAMP)
	$(BIN)/mypy

format: $(STAMP)
	$(BIN)/ruff format . && $(BIN)/ruff check --fix .

# Regenerate the committed sample drive (deterministic for the seed).
sample: $(STAMP)
	rm -rf data_samples/drive
	$(BIN)/roadsurf simulate --scenario sample --seed 7 --out data_samples/drive

clean:
	rm -rf $(VENV) out .pytest_cache .ruff_cache *.egg-info

# README screenshots (docs/img), made by the project's own commands on the demo output.
screenshots: browser-deps
	$(BIN)/roadsurf report $(DEMO_OUT) --screenshot docs/img/report.png
	$(BIN)/roadsurf view $(DEMO_OUT) --serve --web-port 0 --grpc-port 0 --screenshot docs/img/rerun_web.png
