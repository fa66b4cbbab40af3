# mitsuba-p3: `make demo` sets up and renders the built-in example; `make test` sets up and tests.
PYTHON ?= python3
# the demo's evaluation workers: one per core, at most 4 (each holds about 2 GB once compiled)
JOBS ?= $(shell n=$$(nproc 2>/dev/null || echo 1); echo $$(( n < 4 ? n : 4 )))

.PHONY: setup demo test test-all bench references scenes

setup:
	bash scripts/setup.sh

demo: setup
	mitsuba-p3 render scenes/fsclvr.xml -o out/fsclvr.png
	mitsuba-p3 benchmark generate fsclvr --size small --out out/fsclvr-small
	mitsuba-p3 benchmark show out/fsclvr-small -o out/fsclvr-small.png
	mitsuba-p3 fit out/fsclvr-small --out out/model-small --epochs 3
	$(PYTHON) scripts/plot_fit.py out/model-small --samples 12
	mitsuba-p3 infer $$(ls out/fsclvr-small/test/*/0.png | head -1) --model out/model-small -o out/infer-small
	@echo "demo: evaluating the 15 test posteriors without the concept spread (--spread-shots 0, the paper's programs) in $(JOBS) workers"
	mitsuba-p3 evaluate out/fsclvr-small --model out/model-small --out out/eval-small --likelihoods p3 --episodes 50 --spread-shots 0 --jobs $(JOBS)
	@echo "demo: look at out/fsclvr.png, out/fsclvr-small.png, out/model-small/figures/, out/infer-small/ and out/eval-small/"

test: setup
	$(PYTHON) -m pytest -q

test-all: setup
	$(PYTHON) -m pytest -q -m "slow or not slow"

bench: setup
	$(PYTHON) scripts/bench_render.py

references: setup
	$(PYTHON) scripts/make_references.py

scenes: setup
	$(PYTHON) scripts/make_scenes.py
