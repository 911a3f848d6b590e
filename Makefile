# Two commands for a fresh clone (see README.md):
#   make demo   - run the main job
#   make test   - run the test suite
#   make test-slurm - the whole DAG through the SLURM profile on a one-node cluster started here (root)
# Both bootstrap a local virtual environment in .venv by themselves.
PYTHON ?= python3.11
VENV ?= .venv
# torch is installed first and pinned, so nothing else can pull a multi-GB CUDA build by accident.
# On a GPU machine pass the CUDA build instead, e.g.
#   make test TORCH_SPEC="torch==2.13.0" TORCH_INDEX="--index-url <PyTorch CUDA wheel index>"
TORCH_SPEC ?= torch==2.13.0
TORCH_INDEX ?=
PYTEST_ARGS ?=
BIN := $(VENV)/bin
STAMP := $(VENV)/.rtsplat-installed

.PHONY: demo targets family heldout heldout-time convergence results-page family-page raster-demo test test-fast test-slurm lint bench clean-venv chromium

$(STAMP): pyproject.toml
	@command -v $(PYTHON) >/dev/null 2>&1 || { echo "error: $(PYTHON) not found; run 'make PYTHON=python3' with Python >= 3.10"; exit 1; }
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet $(TORCH_SPEC) $(TORCH_INDEX)
	$(BIN)/pip install --quiet -e ".[pipeline,viewer,dev]"
	@touch $@

# The viewer's browser test (tests/test_viewer.py) drives a real Chromium: installed from the Debian
# packages when missing (root needed), never downloaded by playwright.
chromium:
	@command -v chromium >/dev/null 2>&1 || command -v chromium-browser >/dev/null 2>&1 || { \
	  if [ "$$(id -u)" != 0 ]; then echo "error: the viewer test needs Chromium; run 'sudo apt-get install -y chromium' (Debian/Ubuntu) or install Chromium another way"; exit 1; fi; \
	  command -v apt-get >/dev/null 2>&1 || { echo "error: the viewer test needs Chromium and apt-get is not here; install Chromium with this system's package manager"; exit 1; }; \
	  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium; }

# The main job: synthesize a glass dome (Mitsuba 3), then the whole Snakemake DAG (SfM from the
# images, masks, prepare, train the methods of demo/config.yaml, render, metrics, report).
# Result: demo/results/report/index.html. Reruns only redo what changed.
DEMO_VIEWS ?= 80
# One thread per training and rendering job, two jobs at a time: on 2 cores the CPU kernels gain less
# from a second thread than a second job does (README, "Two commands", has the times of both). The fps
# jobs keep their threads (every core of the run), so nothing runs beside the FPS timing.
JOB_THREADS ?= --set-threads train=1 render=1 render_edit=1 video=1
demo: $(STAMP)
	@test -f demo/data/dome/scene.json || $(BIN)/rtsplat synth --scene dome --out demo/data/dome --views $(DEMO_VIEWS) --layers-every 8
	PATH="$(abspath $(BIN)):$$PATH" $(BIN)/snakemake -s Snakefile -d demo --cores 2 $(JOB_THREADS)
	@echo "report: demo/results/report/index.html"

# the benchmark targets: dome + cabin, demo budget and 4x, ablations, half resolution, noise reruns (reuses the demo's jobs)
targets: $(STAMP)
	@test -f demo/data/dome/scene.json || $(BIN)/rtsplat synth --scene dome --out demo/data/dome --views $(DEMO_VIEWS) --layers-every 8
	@test -f demo/data/cabin/scene.json || $(BIN)/rtsplat synth --scene cabin --out demo/data/cabin --views $(DEMO_VIEWS) --layers-every 8
	PATH="$(abspath $(BIN)):$$PATH" $(BIN)/snakemake -s Snakefile -d demo --configfile demo/config.yaml benchmarks/targets.yaml --cores 2 $(JOB_THREADS)
	@echo "report: demo/results/report/index.html"

# the glass-scene family (benchmarks/family.yaml: 20 generated scenes, seeds 0-3: tuning and seen, docs/synth.md):
# RT-Splatting against plain 2DGS with a seed repeat of each, on the datasets' cameras; synthesises each scene the
# config lists into family/data/<kind>-<seed> (80 views, 200x150, layers on the test views), then runs the DAG in
# family/. `make heldout`: the same for the held-out list (benchmarks/heldout.yaml, seeds 100-103) in heldout/,
# to run only when an issue's work is done; nothing is ever chosen from it.
FAMILY_CONFIG ?= benchmarks/family.yaml
FAMILY_DIR ?= family
family: $(STAMP)
	@for scene in $$($(BIN)/python -c "import yaml; print(*yaml.safe_load(open('$(FAMILY_CONFIG)'))['scenes'])"); do \
	  test -f $(FAMILY_DIR)/data/$$scene/scene.json || $(BIN)/rtsplat synth --scene family/$$scene \
	    --out $(FAMILY_DIR)/data/$$scene --views $(DEMO_VIEWS) --layers-every 8 --no-progress || exit 1; done
	PATH="$(abspath $(BIN)):$$PATH" $(BIN)/snakemake -s Snakefile -d $(FAMILY_DIR) --configfile $(FAMILY_CONFIG) --cores 2 $(JOB_THREADS)
	@echo "report: $(FAMILY_DIR)/results/report/index.html"

heldout:
	$(MAKE) family FAMILY_CONFIG=benchmarks/heldout.yaml FAMILY_DIR=heldout

# accuracy against time on held-out scenes (benchmarks/heldout_time.yaml): both methods at 0.5, 1 and 2 times the
# demo's budget on seed 102 of every kind; the report's convergence section gives each RT-Splatting budget against
# 2DGS's finished runs at the same training time. Run once, when the work it judges is done.
heldout-time:
	$(MAKE) family FAMILY_CONFIG=benchmarks/heldout_time.yaml FAMILY_DIR=heldout_time

# converged results (benchmarks/convergence.yaml): RT-Splatting and plain 2DGS at 0.5, 1, 2, 4 and 8 times the demo's
# budget on five tuning scenes of the family (seed 0 of every kind), synthesised into convergence/data/ first; the
# report's convergence section gives the budget at which each method stops gaining, the gap and the layers there
# beside the demo budget's, the time each took and the gap at equal time. About 3 hours on 2 cores (50 trainings;
# measured on the five scenes at 40 views, docs/benchmarks.md).
convergence:
	$(MAKE) family FAMILY_CONFIG=benchmarks/convergence.yaml FAMILY_DIR=convergence

# the page-writing targets refuse a tree with uncommitted changes: the page ($(1)) names the commit its numbers come from
refuse_uncommitted = @test -z "$$(git status --porcelain --untracked-files=no)" || { echo "error: the tree has \
  uncommitted changes; commit or stash them first ($(1) names the commit its numbers come from)"; exit 1; }

# docs/results_family.md (and docs/results_family.report.json): the family in one report from one commit, both halves
# (benchmarks/family_page.yaml: seed 0 and held-out seed 100 of every kind, both methods with a seed repeat, 40
# views) in family-page/ (removed first, so that every run is trained by this commit; about 95 minutes on 2 cores).
# Refuses a tree with uncommitted changes, as results-page does.
FAMILY_PAGE_DIR ?= family-page
family-page: $(STAMP)
	$(call refuse_uncommitted,docs/results_family.md)
	rm -rf $(FAMILY_PAGE_DIR)
	$(MAKE) family FAMILY_CONFIG=benchmarks/family_page.yaml FAMILY_DIR=$(FAMILY_PAGE_DIR) DEMO_VIEWS=40
	$(BIN)/python -m rtsplat.results_page --report $(FAMILY_PAGE_DIR)/results/report --out docs/results_family.md

# docs/results.md (and docs/results.report.json, the report's record it is written from) and the README's picture,
# from one run at the checked-out commit: benchmarks/targets_quick.yaml over the demo's dome and cabin in
# results-page/ (removed first, so that every run is trained by this commit; about an hour on 2 cores), then the
# picture by its recipe (docs/guide/stages.md, "The README's picture"), with the metrics its caption quotes.
# Refuses a tree with uncommitted changes: the page names the commit its numbers come from.
RESULTS_PAGE_DIR ?= results-page
STRIP := $(RESULTS_PAGE_DIR)/strip
results-page: $(STAMP)
	$(call refuse_uncommitted,docs/results.md)
	rm -rf $(RESULTS_PAGE_DIR)
	for scene in dome cabin; do $(BIN)/rtsplat synth --scene $$scene --out $(RESULTS_PAGE_DIR)/data/$$scene \
	  --views $(DEMO_VIEWS) --layers-every 8 --no-progress || exit 1; done
	PATH="$(abspath $(BIN)):$$PATH" $(BIN)/snakemake -s Snakefile -d $(RESULTS_PAGE_DIR) \
	  --configfile demo/config.yaml benchmarks/targets_quick.yaml --cores 2 $(JOB_THREADS)
	$(BIN)/python -m rtsplat.results_page --report $(RESULTS_PAGE_DIR)/results/report --out docs/results.md
	$(BIN)/rtsplat synth --scene dome --out $(STRIP)/dome --views 40 --layers-every 8 --no-progress
	$(BIN)/rtsplat sfm --scene-dir $(STRIP)/dome --out $(STRIP)/sfm
	$(BIN)/rtsplat masks --scene-dir $(STRIP)/dome --out $(STRIP)/masks
	$(BIN)/rtsplat prepare --scene-dir $(STRIP)/dome --sfm $(STRIP)/sfm --masks $(STRIP)/masks --out $(STRIP)/prepared --downsample 1
	$(BIN)/rtsplat train --data $(STRIP)/prepared --out $(STRIP)/run --config demo/config.yaml --scene dome --method rtsplat --quiet
	$(BIN)/rtsplat render --run $(STRIP)/run --data $(STRIP)/prepared --out $(STRIP)/renders
	$(BIN)/rtsplat metrics --renders $(STRIP)/renders --data $(STRIP)/prepared --out $(STRIP)/metrics.json
	$(BIN)/python -m rtsplat.bench.layer_strip --data $(STRIP)/prepared --renders $(STRIP)/renders --out $(STRIP)/demo_strip.png
	cp $(STRIP)/demo_strip.png docs/images/demo_strip.png
	@echo "wrote docs/results.md, docs/results.report.json and docs/images/demo_strip.png at commit $$(git rev-parse --short=12 HEAD);"
	@echo "the picture's caption in README.md quotes $(STRIP)/metrics.json (test PSNR, layers) and that commit"

# the rasterizer alone: a small procedural surfel scene rendered to PNGs in demo_out/
raster-demo: $(STAMP)
	$(BIN)/python -m rtsplat.demo --out demo_out

test: $(STAMP) chromium
	$(BIN)/python -m pytest $(PYTEST_ARGS)

# The whole DAG through `snakemake --profile profiles/slurm` on a one-node SLURM cluster on this machine
# (scripts/slurm_cluster.sh: needs root, installs slurm-wlm and munge with apt when missing), compared with
# a local run of the same DAG, one training job stopped by SLURM and resumed; the cluster is stopped at
# the end whatever happens (tests/test_slurm.py says what is checked).
SLURM_TEST_DIR ?= $${TMPDIR:-/tmp}/rtsplat-test-slurm
test-slurm: $(STAMP)
	trap 'scripts/slurm_cluster.sh down' EXIT; scripts/slurm_cluster.sh up && \
	RTSPLAT_SLURM_REQUIRED=1 OMP_NUM_THREADS=1 $(BIN)/python -m pytest -m slurm -s tests/test_slurm.py \
		--basetemp=$(SLURM_TEST_DIR) $(PYTEST_ARGS)

test-fast: $(STAMP)
	$(BIN)/python -m pytest -m "not slow" $(PYTEST_ARGS)

lint: $(STAMP)
	$(BIN)/ruff check rtsplat tests

bench: $(STAMP)
	$(BIN)/python -m rtsplat.bench.raster
	$(BIN)/python -m rtsplat.bench.effects

clean-venv:
	rm -rf $(VENV)
