# colmap-vc: every target creates or refreshes the local virtual environment itself.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
OUT ?= out

.PHONY: colmap38 chromium mediapipe install demo test test-all test-slow lint typecheck bench bench-synth bodies synthetic docs clean

$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e ".[test,viz]"
	@touch $(STAMP)

install: $(STAMP)

# The main job on the bundled default scene (see docs/quickstart.md).
demo: $(STAMP)
	$(VENV)/bin/colmap-vc demo $(OUT)/demo --overwrite

# Debian's COLMAP 3.8 proves the augmented 3.8 database still maps; its tests skip
# with a reason where it cannot be installed (not root, no apt).
colmap38:
	@command -v colmap >/dev/null 2>&1 || { \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
	    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq colmap >/dev/null) \
	      || echo "could not install Debian's colmap: its tests will skip"; \
	  else echo "not root or no apt-get: Debian's colmap tests will skip"; fi; }

# Debian's Chromium for the report's headless screenshot test (it skips without it).
chromium:
	@command -v chromium >/dev/null 2>&1 || { \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
	    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null) \
	      || echo "could not install Debian's chromium: the report screenshot test will skip"; \
	  else echo "not root or no apt-get: the report screenshot test will skip"; fi; }

# Optional prior estimator (colmap-vc priors): MediaPipe 0.10.14's BlazePose models ship
# inside colmap-vc, ai-edge-litert runs them; MediaPipe itself is not installed.
mediapipe: $(STAMP)
	$(PY) -m pip install -q -e ".[test,viz,mediapipe]"

# Fast tests (slow end-to-end checks are marked and run by test-all / .ci/run).
test: $(STAMP) colmap38 chromium
	$(PY) -m pytest -q

test-all: $(STAMP) colmap38 chromium
	$(PY) -m pytest -q -m "slow or not slow"

lint: $(STAMP)
	$(PY) -m pip install -q ruff==0.17.6
	$(PY) -m ruff check colmap_vc tests bench scripts

typecheck: $(STAMP)
	$(PY) -m pip install -q mypy==2.4.1
	$(PY) -m mypy colmap_vc

# Benchmarks: JSON under bench/out/, tables in docs/.
bench-synth: $(STAMP)
	$(PY) bench/classic.py
	$(PY) bench/synth_speed.py

bench: bench-synth mediapipe
	$(PY) bench/accuracy.py --seeds 0 1
	$(PY) bench/pose2sim.py

# Dev only: re-export the Anny bodies (needs CPU torch, kept out of the core venv).
bodies:
	@test -x .venv-bodies/bin/python || $(PYTHON) -m venv .venv-bodies
	.venv-bodies/bin/pip install -q torch==2.13.0
	.venv-bodies/bin/pip install -q anny==0.6.2 trimesh numpy
	.venv-bodies/bin/python scripts/export_bodies.py --out colmap_vc/data

synthetic: bodies

clean:
	rm -rf $(OUT) bench/out .pytest_cache
