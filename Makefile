# Two commands for a new user: `make all` (installs what is missing, runs the demo or scene=PATH)
# and `make test`. One stage: `make scene=PATH poses` (ingest, poses, normalize, fit, evaluate, export).
SHELL := /bin/bash
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
STAGES := ingest poses normalize fit evaluate export

scene ?=
out ?=
preset ?=
parts ?=
args ?=
set ?=
export OMP_NUM_THREADS ?= $(shell nproc)

RUN_ARGS = $(if $(out),--out $(out)) $(if $(preset),--preset $(preset)) $(foreach s,$(set),--set $(s))

.PHONY: all install test bench status clean $(STAGES)

all: $(STAMP)
ifeq ($(scene),)
	$(PY) -m pipeline demo $(RUN_ARGS)
else
	$(PY) -m pipeline run "$(scene)" $(RUN_ARGS)
endif

$(STAGES): $(STAMP)
ifeq ($(scene),)
	$(PY) -m pipeline demo --until $@ $(RUN_ARGS)
else
	$(PY) -m pipeline $@ "$(scene)" $(RUN_ARGS)
endif

status: $(STAMP)
ifeq ($(scene),)
	$(PY) -m pipeline status out/demo/demo-photos/images --out out/demo --preset $(or $(preset),fast) $(foreach s,$(set),--set $(s))
else
	$(PY) -m pipeline status "$(scene)" $(RUN_ARGS)
endif

install: $(STAMP)

# torch is installed on its own first, pinned, so that no other package can pull a newer (CUDA) build.
$(STAMP): pyproject.toml setup.py $(wildcard csrc/*)
	@test -x $(PY) || python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip setuptools wheel ninja "numpy>=1.26,<3"
	$(PY) -c "import torch" 2>/dev/null || $(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q --no-build-isolation -e '.[test]'
	$(PY) setup.py -q build_ext --inplace
	$(PY) -c "import plenoxels._C" && touch $(STAMP)

test: $(STAMP)
	$(PY) -m pytest -q tests

# make bench [parts="fit scaling"] [args="..."]: every benchmark part, or the ones named (bench/__main__.py
# lists them); args go to a single named part (make bench parts=fit args="--presets fast,default").
bench: $(STAMP)
	$(PY) -m bench $(parts) $(if $(args),-- $(args))

clean:
	rm -rf build out bench/out plenoxels/*.so
