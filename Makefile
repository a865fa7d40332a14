# Two commands for a newcomer: `make demo` and `make test`. Both set up first.
SHELL := /bin/bash
.DEFAULT_GOAL := help
PYTHON ?= python3
VENV := $(CURDIR)/.venv
VENV_STAMP := $(VENV)/.stance-requirements
BUILD_STAMP := $(CURDIR)/install/.stance-build
# Python packages are symlink-installed: only packaging, interface and data files need a rebuild.
WORKSPACE_SOURCES := colcon.meta $(shell find msgs src cmake -type f \( -name package.xml -o -name setup.py \
  -o -name setup.cfg -o -name CMakeLists.txt -o -name '*.cmake' -o -name '*.msg' -o -name '*.srv' \
  -o -name '*.action' -o -path '*/config/*' -o -path '*/resource/*' -o -path '*/launch/*' \) 2>/dev/null)
ENV := source $(CURDIR)/env.sh &&

.PHONY: help setup demo test bench clean
help:
	@echo "make demo   set up, then plan and execute a multi-contact motion on Talos (bag, plots, checks)"
	@echo "make test   set up, then run every test"
	@echo "make bench  set up, then run the benchmarks"
	@echo "make setup  build .venv and the colcon workspace, compile pik_node's kernels"

# numba compiles pik_node's kernels in about 1.5 minutes (Talos' four shipped configurations,
# limit files x hierarchies), then loads them from its disk cache (keyed on the library's
# sources) in under a second: compile them here, not at a node's start.
setup: $(BUILD_STAMP)
	$(ENV) stance compile

$(VENV_STAMP): requirements.txt
	test -x $(VENV)/bin/python || $(PYTHON) -m venv $(VENV)
	$(VENV)/bin/python -m pip install --quiet --disable-pip-version-check -r requirements.txt
	touch $@

$(BUILD_STAMP): $(VENV_STAMP) $(WORKSPACE_SOURCES)
	export VIRTUAL_ENV=$(VENV) PATH=$(VENV)/bin:$$PATH AMENT_PREFIX_PATH=$(VENV) CMAKE_PREFIX_PATH=$(VENV) && \
	colcon --log-base build/log build --base-paths msgs src --build-base build --install-base install --symlink-install \
	  --event-handlers console_cohesion- summary+ status- \
	  --cmake-args -DPython3_EXECUTABLE=$(VENV)/bin/python \
	  -DCMAKE_PROJECT_INCLUDE=$(CURDIR)/cmake/drop_missing_include_dirs.cmake
	touch $@

demo: setup
	$(ENV) stance demo

test: setup
	$(ENV) python -m pytest tests

bench: setup
	$(ENV) stance bench

clean:
	rm -rf build install log
