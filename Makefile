# mitsuba-p3: `make demo` sets up and renders the built-in example; `make test` sets up and tests.
PYTHON ?= python3

.PHONY: setup demo test test-all bench references scenes

setup:
	bash scripts/setup.sh

demo: setup
	mitsuba-p3 render scenes/fsclvr.xml -o out/fsclvr.png
	mitsuba-p3 render scenes/room.xml --shape cube --color blue --material metal --theta 30 --shadows -o out/room-cube.png
	@echo "demo: look at out/fsclvr.png and out/room-cube.png"

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
