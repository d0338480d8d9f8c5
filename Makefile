# Two commands do everything on a fresh machine: `make demo` and `make test` (each creates .venv if missing).
# Daily work: `make check` (the tests not marked slow, under 2 minutes once numba's cache is warm) and `make lint`.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
DEMO := demo_out

.PHONY: demo test check lint bench venv clean

venv: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[dev]"
	touch $(STAMP)

# The main job on a sample the project makes: a synthetic street scanned by a 64-beam LiDAR on a car driving it
# (16 frames 1 m apart, as a 10 Hz scanner at 36 km/h), reconstructed tile by tile on a local Dask cluster with
# the car's trajectory (sensor origins: walls face the street, shadows stay open), then scored against its
# ground-truth mesh, over the observed region and over the footprint (truth within 1.5 and 3 m of a point: holes
# between scan lines count as misses).
demo: $(STAMP)
	$(VENV)/bin/tiled-gridpull sample street $(DEMO) --points 300000 --frames 16 --origin 500000 4000000 100
	$(VENV)/bin/tiled-gridpull reconstruct $(DEMO)/street.laz -o $(DEMO)/street_mesh.ply --config configs/scene.yaml \
		--trajectory $(DEMO)/street_trajectory.csv
	$(VENV)/bin/tiled-gridpull evaluate $(DEMO)/street_mesh.ply $(DEMO)/street_gt.ply --observed $(DEMO)/street.laz --thresholds 0.05 0.1 0.2 \
		--footprint 1.5 3

# the full suite, slow end-to-end tests included (what CI runs), in TEST_JOBS processes (a test file stays in one,
# so its module fixtures are computed once; files go out longest first, as tests/conftest.py orders them)
TEST_JOBS ?= 2
test: $(STAMP)
	$(PY) -m pytest -q -n $(TEST_JOBS) --dist loadfile --no-loadscope-reorder

# the fast tier: everything not marked slow
check: $(STAMP)
	$(PY) -m pytest -q -m "not slow"

lint: $(STAMP)
	$(PY) -m ruff check tiled_gridpull pipeline tests benchmarks

bench: $(STAMP)
	$(PY) -m pip install --quiet -e ".[bench]"
	$(PY) -m benchmarks.shapes all
	$(PY) -m benchmarks.floor
	$(PY) -m benchmarks.scenes street --points 1000000 4000000 14000000
	$(PY) -m benchmarks.dask_overhead 1000 10000 100000
	$(PY) benchmarks/report.py

clean:
	rm -rf $(DEMO) .pytest_cache
