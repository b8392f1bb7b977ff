# shadowopt: `make demo` sets everything up and runs the main job on the demo scene; `make serve` serves it;
# `make test` sets up and tests.
# Both are idempotent: the set-up re-runs only when requirements.lock or pyproject.toml change.
SHELL := /bin/bash
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.shadowopt-setup
LOG := $(VENV)/setup.log
APT_PKGS := libllvm19 libegl1 libegl-mesa0 libgl1-mesa-dri
# glslang-tools and spirv-cross: the HLSL shader listings of docs/engine-integration.md are compiled by their test.
APT_PKGS += glslang-tools spirv-cross
# chromium: the browser inspector's tests (tests/test_inspect_browser.py) drive Debian's Chromium headless through Playwright.
APT_PKGS += chromium
SUDO := $(shell [ "$$(id -u)" = 0 ] || echo sudo)
# Dr.Jit needs libLLVM >= 16 (Debian's libllvm19); 15 crashes at the first kernel, 14 is refused.
export DRJIT_LIBLLVM_PATH ?= $(firstword $(wildcard /usr/lib/*-linux-gnu/libLLVM.so.19.1) /usr/lib/x86_64-linux-gnu/libLLVM.so.19.1)
HOST ?= 127.0.0.1
PORT ?= 8000

# The web engines, pinned, for the emitted modules' browser tests (tests/test_three_module.py, test_babylon_module.py,
# test_filament_module.py, test_tune_three.py) and `shadowopt bench engines`: npm's packages into out/web, outside
# git, in one npm install (one resolution of the prefix instead of three); no install script runs and no binary is
# downloaded (three.js with its CSM addon; @babylonjs/core: ES modules, no dependencies; filament: filament.js,
# filament.wasm and filament.d.ts as npm ships them, its one dependency gl-matrix along). Re-run only when a pin
# changes: the stamp names the versions.
THREE_VERSION := 0.187.0
BABYLON_VERSION := 9.35.0
FILAMENT_VERSION := 1.53.4
WEB := out/web
WEB_PACKAGES := three@$(THREE_VERSION) @babylonjs/core@$(BABYLON_VERSION) filament@$(FILAMENT_VERSION)
WEB_STAMP := $(WEB)/.web-three-$(THREE_VERSION)-babylon-$(BABYLON_VERSION)-filament-$(FILAMENT_VERSION)

.PHONY: setup serve test test-fast bench demo clean mutate

setup: $(STAMP) $(WEB_STAMP)

$(WEB_STAMP):
	@command -v npm >/dev/null 2>&1 || { echo "setup: apt-get install nodejs npm"; \
	  $(SUDO) apt-get update -qq && DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -qq nodejs npm >/dev/null; }
	@echo "setup: npm install $(WEB_PACKAGES) into $(WEB)"
	@mkdir -p $(WEB)
	@npm install --prefix $(WEB) --save-exact --no-audit --no-fund --ignore-scripts $(WEB_PACKAGES) >$(WEB)/npm.log 2>&1 || { cat $(WEB)/npm.log; exit 1; }
	@rm -f $(WEB)/.web-* $(WEB)/.three-* $(WEB)/.babylon-* $(WEB)/.filament-*
	@touch $@

$(STAMP): requirements.lock pyproject.toml
	@missing=""; for p in $(APT_PKGS); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	if [ -n "$$missing" ]; then echo "setup: apt-get install$$missing"; \
	  $(SUDO) apt-get update -qq && DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -qq $$missing >/dev/null; fi
	@[ -x $(PY) ] || { echo "setup: creating $(VENV)"; python3 -m venv $(VENV); }
	@echo "setup: installing pinned Python dependencies into $(VENV) (first time: a few minutes)"
	@$(PY) -m pip install -q --upgrade pip >>$(LOG) 2>&1 || { cat $(LOG); exit 1; }
	@# The CPU build of torch, asked for by its local version; TORCH_FIND_LINKS may name a folder of wheels.
	@# Byte-compiled at install (no --no-compile): with PYTHONDONTWRITEBYTECODE set, as on this project's machines,
	@# Python never writes what it compiles, and every process (each xdist worker, server, loader child and CLI run)
	@# would compile torch, NumPy and the rest from source again (TESTING.md).
	@$(PY) -m pip install -q $(if $(TORCH_FIND_LINKS),--find-links $(TORCH_FIND_LINKS)) \
	  $(if $(wildcard /opt/wheels),--find-links /opt/wheels) "torch==2.13.0+cpu" >>$(LOG) 2>&1 || { cat $(LOG); exit 1; }
	@$(PY) -m pip install -q -r requirements.lock >>$(LOG) 2>&1 || { cat $(LOG); exit 1; }
	@$(PY) -m pip install -q --no-deps -e . >>$(LOG) 2>&1 || { cat $(LOG); exit 1; }
	@touch $(STAMP)
	@echo "setup: done"

serve: setup
	$(VENV)/bin/shadowopt serve --host $(HOST) --port $(PORT)

# Every layer (TESTING.md: unit, server, browser, gl; slow ones included). Exit code 5 (no test collected) fails too.
# The files run on two pytest-xdist workers (--dist loadfile: a file's module server is started once); three on the
# 2 cores were slower on a fresh clone (pytest 10 min 30 s against 9 min 52 s, TESTING.md); TEST_JOBS=1 runs them in
# one process.
# --no-loadscope-reorder: the files are handed out in tests/conftest.py's order (heavy_files_first: files with slow,
# then server/browser/gl tests first), not xdist's most-tests-first, which left two of the longest files for the end.
# The slowest 20 tests are printed at the end.
TEST_JOBS ?= 2
test: setup
	$(PY) -m pytest -q --durations=20 $(if $(filter-out 0 1,$(TEST_JOBS)),-n $(TEST_JOBS) --dist loadfile --no-loadscope-reorder)

# The unit layer without its slow tests: no server, browser or OpenGL, on the same TEST_JOBS workers as `make test`
# (1,183 tests: 91.6 s on two workers; 1,053 took 142 s in one process; quiet 2-core machine, TESTING.md). One layer:
# `$(PY) -m pytest -m server`; schemathesis' plugin is left out (only the server layer's fuzzing needs it).
test-fast: setup
	$(PY) -m pytest -q -m "unit and not slow" -p no:schemathesis $(if $(filter-out 0 1,$(TEST_JOBS)),-n $(TEST_JOBS) --dist loadfile --no-loadscope-reorder)

# Sampled mutation testing with cosmic-ray's operators (tests/mutation/run.py; the sample, the module -> tests map
# and the time budget in tests/mutation/config.json): scores per folder into TESTING.md, survivors into
# tests/mutation/survivors.md. MUTATE_ARGS="--budget 600 --per-folder 5" or "--only ID ..." to re-run mutants.
mutate: setup
	$(PY) tests/mutation/run.py $(MUTATE_ARGS)

bench: setup
	$(VENV)/bin/shadowopt bench coarse

# The main job on the bundled demo scene: an optimized setup, measured against ray-traced shadows,
# and every method side by side (heatmaps and table in out/demo/).
demo: setup
	$(VENV)/bin/shadowopt optimize configs/demo_scene.usda --rig configs/demo_rig.json --method optimized --out out/demo/solution.json
	$(VENV)/bin/shadowopt evaluate configs/demo_scene.usda --rig configs/demo_rig.json --solution out/demo/solution.json --screen 640x360 --heatmap out/demo/optimized_heatmap.png
	$(VENV)/bin/shadowopt compare configs/demo_scene.usda --rig configs/demo_rig.json --methods uniform,focused,lispsm,logpsm,optimized --screen 640x360 --report out/demo

clean:
	rm -rf $(VENV) out .pytest_cache
