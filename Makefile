# vet: two commands set everything up on a fresh clone: `make demo` and `make test`.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
VET    := $(BIN)/vet
STAMP  := $(VENV)/.installed

.PHONY: demo test test-slow fuzz bench evaluate-shared evaluate-stream evaluate-rig evaluate-exposure batch-acceptance lint format sample-data test-hardware test-tools sample-hdr clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[dev]'
	touch $(STAMP)

venv: $(STAMP)

DEMO_DIR := demo_out
# The demo makes its folder afresh (vet replaces no existing output without --force).
demo: $(STAMP)
	@rm -rf $(DEMO_DIR) && mkdir -p $(DEMO_DIR)
	$(VET) simulate builtin:interior --size 640x512 --seed 1 -o $(DEMO_DIR)/still.exr
	$(VET) hdr-static $(DEMO_DIR)/still.exr -o $(DEMO_DIR)/still.hdr.exr
	$(VET) tonemap $(DEMO_DIR)/still.hdr.exr -o $(DEMO_DIR)/still.png
	$(VET) tonemap $(DEMO_DIR)/still.exr --exposure-time-map -o $(DEMO_DIR)/exposure_time.png
	$(VET) simulate builtin:interior --size 640x512 --seed 1 --motion translate:30,0 -o $(DEMO_DIR)/pan.exr
	$(VET) hdr-static $(DEMO_DIR)/pan.exr -o $(DEMO_DIR)/pan.static.exr
	$(VET) deblur $(DEMO_DIR)/pan.exr -o $(DEMO_DIR)/pan.deblur.exr --motion-picture $(DEMO_DIR)/pan.motion.png
	$(VET) tonemap $(DEMO_DIR)/pan.static.exr -o $(DEMO_DIR)/pan.static.png
	$(VET) tonemap $(DEMO_DIR)/pan.deblur.exr -o $(DEMO_DIR)/pan.deblur.png
	@echo "demo: still scene: $(DEMO_DIR)/still.png and $(DEMO_DIR)/exposure_time.png;" \
	      "panning 30 px/s: $(DEMO_DIR)/pan.static.png (I/T, blurred) vs $(DEMO_DIR)/pan.deblur.png" >&2

# The suite on every core (pytest-xdist); a document's examples stay on one worker, in order.
test: $(STAMP)
	$(BIN)/python -m pytest -q -n auto --dist loadgroup

test-slow: $(STAMP)
	$(BIN)/python -m pytest -q -m slow -n auto --dist loadgroup

# GenICam cameras (issue 20): Debian's Aravis (its fake GigE Vision camera included) and
# PyGObject in the venv, then the camera tests against two fake cameras on loopback (the
# second on 127.0.0.2, added to lo when root may; else one fake camera and a recorded frame).
SUDO := $(shell [ "$$(id -u)" = 0 ] || echo sudo)
test-hardware: $(STAMP)
	$(SUDO) apt-get install -y -q aravis-tools gir1.2-aravis-0.8 libgirepository1.0-dev libcairo2-dev pkg-config
	$(BIN)/pip install --quiet 'PyGObject<3.51'
	-ip addr show lo | grep -q 127.0.0.2 || $(SUDO) ip addr add 127.0.0.2/8 dev lo
	VET_REQUIRE_HARDWARE=1 $(BIN)/python -m pytest -q -rs tests/test_genicam.py

# A longer fuzz campaign than `make test` runs (issue 22): CASES mutated files of each kind
# through every command that reads them, then CASES valid and CASES mutated captures of
# the metadata relations generator (hypothesis, tests/fuzz_meta.py); prints counts per
# reader and outcome. BAD: an internal error, a run over 10 s, a non-finite output.
CASES ?= 300
fuzz: $(STAMP)
	$(BIN)/python -m tests.fuzz $(CASES) 2

# Other tools read vet's files (issue 21): Debian's pfstools, then the tests that pipe
# vet's HDR files through pfsin | pfstmo_drago03 | pfsout (they skip in make test without it).
test-tools: $(STAMP)
	$(SUDO) apt-get install -y -q pfstools
	$(BIN)/python -m pytest -q -rs tests/test_pfstools.py

bench: $(STAMP)
	$(BIN)/python -m tests.benchmarks.run

# Issue 3's acceptance sweep: vet evaluate on every ../shared/data/hdr scene, two motions
# (~35 min). REACH=N dims the scenes alike (p99.9 reaches the threshold in N subframes)
# and writes eval_out_nN/.
evaluate-shared: $(STAMP)
	$(BIN)/python -m tests.benchmarks.evaluate_shared $(if $(REACH),eval_out_n$(REACH) --reach-subframes $(REACH),eval_out)

# Issue 18's acceptance sweep (~20 min): default deblur against the burst merge of its own
# measuring stream, hdr-static and the oracle, every shared scene at 320x240, with
# translate:30,0, an object on dark content, rotate:4 and shake:4; table and tally.
evaluate-stream: $(STAMP)
	$(BIN)/python -m tests.benchmarks.evaluate_stream eval_stream

# Issue 20's deblur point (~15 min): the realistic rig profile, every shared scene at
# 320x240, translate:30,0 and an object on dark content; deblur vs hdr-static and oracle.
evaluate-rig: $(STAMP)
	$(BIN)/python -m tests.benchmarks.evaluate_rig eval_rig

# The comparison methods alone on the same runs: the scenes dimmed 1-16x (~12 min), then
# DESIGN's brightness with seeds 0-4 (~12 min).
evaluate-exposure: $(STAMP)
	$(BIN)/python -m tests.benchmarks.exposure_sweep eval_exposure
	$(BIN)/python -m tests.benchmarks.exposure_sweep eval_exposure/seeds --reach 1 --seeds 0,1,2,3,4

# Issue 5's acceptance at full scale: 20 captures + 2 corrupt, rerun, kill -9, a separate
# Dask scheduler with two workers, make -j2 with make/vet.mk.
batch-acceptance: $(STAMP)
	$(BIN)/python -m tests.benchmarks.batch_acceptance

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

format: $(STAMP)
	$(BIN)/ruff format .
	$(BIN)/ruff check --fix .

sample-data: $(STAMP)
	$(BIN)/python -m stages.sample_data sample_data

# The shipped Make recipes (make/vet.mk) on the sample captures; try `make -j2 sample-hdr`.
sample-hdr: $(STAMP)
	$(MAKE) -f make/vet.mk VET=$(abspath $(VET)) CAPTURES=sample_data/captures OUT=sample_out vet-all

clean:
	rm -rf $(DEMO_DIR) sample_out eval_out eval_out_n* eval_exposure .pytest_cache
