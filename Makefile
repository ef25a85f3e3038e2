# Two commands do all the set-up on a fresh machine:
#   make demo   # installs into .venv, then runs the demo on the built-in sensor design
#   make test   # installs into .venv, then runs the test suite and the quick benchmark gates
PY ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-stamp
OUT ?= demo_out

.PHONY: setup demo test test-fast bench clean

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	# the cluster extra too: CI runs the sweep tests on a real local Dask cluster (tests/test_cluster.py);
	# and the report extra (its browser is installed below)
	$(BIN)/python -m pip install -q -e '.[test,cluster,report]'
	# pyrender pins PyOpenGL 3.1.0, whose EGL/OSMesa paths fail on Mesa 22 / numpy 2; 3.1.10 works
	# (pip then prints a resolver warning about pyrender's pin, which is expected).
	$(BIN)/python -m pip install -q 'PyOpenGL==3.1.10' 2>&1 | grep -v "pyrender 0.1.45 requires\|dependency conflicts\|Location" || true
	$(BIN)/python -c "import mujoco, pyrender, cv2, trimesh, scipy, numpy, numba, pyarrow, distributed"
	# OSMesa is the fallback GL back end; where it is missing and this is root with apt (CI), install Debian's
	# libosmesa6 so the tests compare its frames with EGL's (otherwise that test skips and says why)
	@$(PY) -c "import ctypes.util, sys; sys.exit(ctypes.util.find_library('OSMesa') is None)" || \
	  { [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null && apt-get install -y -q libosmesa6 >/dev/null 2>&1 \
	    && echo "installed libosmesa6 (OSMesa back end)"; } || echo "note: libosmesa6 not installed; the OSMesa test will skip"
	# the report extra's browser: tests/test_report_browser.py opens report.html in a real headless Chromium
	# (and `stereotactip report` paints report.png with it); where none is found and this is root with apt (CI),
	# install Debian's chromium (~110 MB download). Without it those tests skip, except under CI=true: they fail.
	@$(PY) -c "import shutil, sys; sys.exit(not any(map(shutil.which, ('chromium', 'chromium-browser', 'google-chrome'))))" || \
	  { [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null && \
	    { DEBIAN_FRONTEND=noninteractive apt-get install -y -q chromium >/dev/null 2>&1 || \
	      { apt-get update -q >/dev/null 2>&1 && DEBIAN_FRONTEND=noninteractive apt-get install -y -q chromium >/dev/null 2>&1; }; } \
	    && echo "installed chromium (report checks in a headless browser)"; } || \
	  echo "note: chromium not installed; the report browser tests will skip (and fail under CI=true)"
	# compile the pipeline's numba kernels once (~30-35 s here); cached in each package's __pycache__
	$(BIN)/python -c "from pipeline.warmup import compile_kernels; print(f'pipeline kernels ready in {compile_kernels():.1f} s')"
	touch $(STAMP)

setup: $(STAMP)

demo: $(STAMP)
	$(BIN)/stereotactip demo --out $(OUT)

# the test files spread over every core (pytest-xdist; a file's tests stay together, so a module's fixtures are
# built once); each physics press is single-threaded
PYTEST := $(BIN)/python -m pytest -q -n auto --dist loadfile

test: $(STAMP)
	$(PYTEST)
	$(BIN)/stereotactip bench all --quick --check --calibration estimated --out results/ci-quick

test-fast: $(STAMP)
	$(PYTEST) -m "not slow"

bench: $(STAMP)
	$(BIN)/stereotactip bench all --out results/full

clean:
	rm -rf $(VENV) $(OUT) results .pytest_cache
