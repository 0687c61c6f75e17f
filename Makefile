# Two entry points: `make demo` and `make test`. Both do all set-up first.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
# root here; elsewhere apt needs sudo
SUDO := $(shell [ "$$(id -u)" = 0 ] || echo sudo)
APT_PACKAGES := python3-venv python3-dev gcc pkg-config libgirepository1.0-dev libcairo2-dev \
	gir1.2-aravis-0.8 aravis-tools-cli xvfb x11-xserver-utils xserver-xorg-core \
	xserver-xorg-video-dummy iproute2 util-linux libgl1 libegl1 mesa-vulkan-drivers
STAMP := $(VENV)/.installed

.PHONY: setup demo test lint bench bench-capture bench-batch eval clean

setup: $(STAMP)

$(VENV)/.apt: Makefile
	@if ! dpkg -s $(APT_PACKAGES) >/dev/null 2>&1; then \
	  echo "installing apt packages: $(APT_PACKAGES)"; \
	  $(SUDO) apt-get update -qq && \
	  DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -qq --no-install-recommends $(APT_PACKAGES) >/dev/null; \
	fi
	@mkdir -p $(VENV) && touch $@

$(STAMP): $(VENV)/.apt requirements.lock pyproject.toml
	@[ -x $(BIN)/python ] || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --disable-pip-version-check -r requirements.lock
	$(BIN)/python -m pip install -q --disable-pip-version-check --no-deps --no-build-isolation -e .
	$(BIN)/rerun analytics disable >/dev/null 2>&1 || true
	@touch $@

demo: setup
	$(BIN)/lightflow demo

# The suite runs in a private network namespace: Aravis discovery and the
# GigE Vision simulator never send a packet off this machine.
NETNS := $(shell [ "$$(id -u)" = 0 ] && echo "unshare --net" || echo "unshare --net --map-root-user")
test: setup
	$(BIN)/ruff check .
	$(NETNS) sh -c 'ip link set lo up && exec $(BIN)/python -m pytest -q $(PYTEST_ARGS)'

bench: setup
	$(BIN)/lightflow bench --frames 30
	$(BIN)/lightflow bench --recorder --frames 5

# Live capture from Aravis's GigE Vision simulator (loopback, private netns):
# three cold runs of `capture --record --lossless`, with one core kept busy; then
# 1600x1200 at 30 fps with Rerun, the simulator streaming a rendered board.
bench-capture: setup
	$(NETNS) sh -c 'ip link set lo up && cd tests && ../$(BIN)/python bench_capture.py --runs 3 --hog && \
	  ../$(BIN)/python bench_capture.py --runs 1 --size 1600x1200 --fps 30 --frames 300 --rerun --scene board'

# `lightflow batch` on a local Dask cluster: frames/s with 1 and 2 workers, 32-worker estimate
# (4 recordings of 60 frames at 1600x1200, cycled from 4 rendered frames).
BENCH_BATCH := out/bench-batch
bench-batch: setup
	[ -f $(BENCH_BATCH)/rec/recording.json ] || $(BIN)/lightflow simulate --scene board --frames 4 --out $(BENCH_BATCH)/rec
	$(BIN)/lightflow batch $(BENCH_BATCH)/rec --out $(BENCH_BATCH)/runs --chunk-frames 30 --bench

# Accuracy: the evaluation matrix (generated rigs x every scene x the paper's
# exposures; see `lightflow eval --help`), printed as the README's table.
# Recordings are kept in out/eval/matrix and reused by the next run; a picture
# of each case (error map, causes of no depth) goes to out/eval/pictures.
EVAL := out/eval
eval: setup
	mkdir -p $(EVAL)
	$(BIN)/lightflow eval --matrix $(EVAL)/matrix --frames 2 --stages --pictures $(EVAL)/pictures

clean:
	rm -rf $(VENV) .pytest_cache build *.egg-info
