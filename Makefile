# dmd_jax — every target creates the venv from pyproject.toml first if needed.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-stamp
PYTEST_WORKERS ?= 2

.PHONY: install test test-slow lint format bench bench-inference bench-inference-scale bench-training ablate ablate-quick ablate-smoke ablate-gpu bench-device sota demo sota-lite

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --upgrade pip
	$(BIN)/pip install -e '.[dev]'
	touch $(STAMP)

install: $(STAMP)

test: $(STAMP)
	$(BIN)/python -m pytest -n $(PYTEST_WORKERS) --dist loadfile -q --durations=15

test-slow: $(STAMP)
	$(BIN)/python -m pytest -n $(PYTEST_WORKERS) --dist loadfile -q -m slow --durations=15

lint: $(STAMP)
	$(BIN)/ruff check dmd_jax tests experiments benchmarks notebooks
	$(BIN)/ruff format --check dmd_jax tests experiments benchmarks notebooks

format: $(STAMP)
	$(BIN)/ruff format dmd_jax tests experiments benchmarks notebooks
	$(BIN)/ruff check --fix dmd_jax tests experiments benchmarks notebooks

# Benchmarks are scripts, not tests; results go to benchmarks/results/ (see its README).
# glibc.malloc.hugetlb=1 backs JAX's large buffers with transparent huge pages, as NumPy
# already does for its own arrays; the second run measures the default allocator.
bench: $(STAMP)
	GLIBC_TUNABLES=glibc.malloc.hugetlb=1 $(BIN)/python benchmarks/bench_aggregation.py
	$(BIN)/python benchmarks/bench_aggregation.py --name aggregation_default_malloc \
		--sizes 100000 300000 1000000 --widths 64 --methods ell --meshes
	$(MAKE) bench-inference bench-training bench-cold bench-vertex-update bench-passes

# The normal-first head's vertex update, Jacobi steps and the converged solve, against the
# whole default denoise call at 100k faces in the same process (vertex_update.md; issue 57).
.PHONY: bench-vertex-update
bench-vertex-update: $(STAMP)
	$(BIN)/python benchmarks/bench_vertex_update.py

# What each network pass of denoise costs (Jacobi and the solve, 1-8 passes) beside bnf
# at 100k faces, one process: pass_cost.md.
.PHONY: bench-passes
bench-passes: $(STAMP)
	$(BIN)/python benchmarks/bench_pass_cost.py --faces 100000 --repeat 5

# Cold start (issues 58, 64): fresh dmd-jax denoise processes with an empty cache, after
# another mesh, after dmd-jax warmup, beside bnf; cold_start.md.
.PHONY: bench-cold
bench-cold: $(STAMP)
	$(BIN)/python benchmarks/bench_cold_start.py --repeat 3 --profile

# Inference scaling and training throughput, each command under 10 minutes (--append
# adds to the same report).
HUGE := GLIBC_TUNABLES=glibc.malloc.hugetlb=1
bench-inference: $(STAMP)
	$(HUGE) $(BIN)/python benchmarks/bench_inference.py --presets small \
		--faces 1000 3000 10000 30000 100000 300000
	$(HUGE) $(BIN)/python benchmarks/bench_inference.py --presets small --faces 1000000 --append
	$(HUGE) $(BIN)/python benchmarks/bench_inference.py --presets paper \
		--faces 1000 3000 10000 30000 --append
	$(HUGE) $(BIN)/python benchmarks/bench_inference.py --presets paper \
		--faces 100000 300000 1000000 --append
	$(MAKE) bench-inference-scale

# Millions of faces under a 6.5 GiB budget (patch-wise; issue 17): one fresh process per
# size, inference_scale.md. Each size takes minutes (the 20M one most of an hour on 2
# shared cores); --append keeps the other sizes' rows.
bench-inference-scale: $(STAMP)
	$(BIN)/python benchmarks/bench_inference_scale.py --presets small \
		--faces 1000000 --modes default patches --append
	$(BIN)/python benchmarks/bench_inference_scale.py --presets small \
		--faces 5000000 10000000 20000000 --append
	$(BIN)/python benchmarks/bench_inference_scale.py --presets paper \
		--faces 1000000 3000000 --append
	$(BIN)/python benchmarks/bench_io.py --faces 2000000 20000000

# The long run's training steps per CPU second with the candidate pool
# (train.candidate_pool) against today's recipe, in one process (issue 62 item 3):
# results/train_long_speed.md. No GLIBC_TUNABLES: the run is started without them.
.PHONY: bench-train
bench-train: $(STAMP)
	$(BIN)/python benchmarks/bench_train_long.py --uses 4 8

bench-training: $(STAMP)
	$(HUGE) $(BIN)/python benchmarks/bench_training.py --presets test
	$(HUGE) $(BIN)/python benchmarks/bench_training.py --presets small --append
	$(HUGE) $(BIN)/python benchmarks/bench_training.py --presets paper --append

# WEIGHTS=path/to/file.msgpack runs either target with other weights than the bundled ones.
demo: $(STAMP)
	$(BIN)/dmd-jax demo --out out/demo --overwrite $(if $(WEIGHTS),--weights $(WEIGHTS))

# Quality scripts live in benchmarks/quality/ (the protocol: dmd_jax/protocol.py).
# Every mesh of ../shared/meshes at 3 noise levels; writes benchmarks/results/sota_lite.{md,csv}.
sota-lite: $(STAMP)
	$(BIN)/python benchmarks/quality/sota_lite.py $(if $(WEIGHTS),--weights $(WEIGHTS))
	$(MAKE) headroom

# The normal-first head's headroom (issue 57) on sota-lite's meshes and conditions: the
# error of ground-truth normals, of the candidates' per-face oracle, of the best candidate
# field and of the network, each through the 10-step and the converged vertex update; the
# default call rated per shape against sota_lite.csv's other denoisers. A diagnostic
# (benchmarks/results/headroom.{md,csv}); nothing in denoise reads it.
.PHONY: headroom
headroom: $(STAMP)
	$(BIN)/python benchmarks/quality/headroom.py --others benchmarks/results/sota_lite.csv $(if $(WEIGHTS),--weights $(WEIGHTS))

# Executes the notebook scripts notebooks/NN_*.py (percent format, the only source); the
# executed notebooks go to notebooks/executed/ (git-ignored).
# 05 and 06 need the bundled weights, or WEIGHTS=path/to/file.msgpack.
.PHONY: notebooks
notebooks: $(STAMP)
	$(if $(WEIGHTS),DMD_JAX_WEIGHTS=$(WEIGHTS)) $(BIN)/python notebooks/_run.py

# One notebook: `make notebook NB=05` (its number, or any prefix of its name that
# matches one notebook), executed into notebooks/executed/ like `make notebooks`.
NB_FILE = $(wildcard notebooks/$(NB)*.py)
.PHONY: notebook
notebook: $(STAMP)
	@test -n "$(NB)" || { echo "usage: make notebook NB=05 (one of: $(notdir $(basename $(wildcard notebooks/[0-9]*.py))))"; exit 2; }
	@test $(words $(NB_FILE)) -eq 1 || { echo "NB=$(NB) matches $(words $(NB_FILE)) notebooks: $(notdir $(NB_FILE))"; exit 2; }
	$(if $(WEIGHTS),DMD_JAX_WEIGHTS=$(WEIGHTS)) $(BIN)/python notebooks/_run.py --only $(notdir $(NB_FILE))

# The long training run that outlives sessions (scripts/train_long.sh, dmd_jax/long_run.py):
# train-long resumes it from the committed training/long_run.msgpack (or the workdir, when
# ahead) at nice 19 in the background, bit-identically; train-long-save stops it cleanly
# and commits its state and curve; train-long-status prints one line. OUT=dir picks the
# run folder (default runs/long). Every session: train-long at its start, save at its end.
# train-long-milestone scores the run's latest milestone (STEP=10000: that one), kept every
# 10,000 steps, against the bundled weights and appends the verdict to train_long.md.
.PHONY: train-long train-long-save train-long-status train-long-milestone train-long-candidate
train-long: $(STAMP)
	scripts/train_long.sh $(if $(OUT),$(OUT),runs/long)

train-long-save: $(STAMP)
	scripts/train_long_save.sh $(if $(OUT),$(OUT),runs/long)

train-long-status: $(STAMP)
	@$(BIN)/python -m dmd_jax.long_run status --workdir $(if $(OUT),$(OUT),runs/long)/ft \
		--state training/long_run.msgpack

train-long-milestone: $(STAMP)
	STEP=$(STEP) scripts/train_long_milestone.sh $(if $(OUT),$(OUT),runs/long)

# The milestone scored with the smoothing controller trained for its network (the bundling
# rule's "controller retrained for it"): its set searched again (~55 min on 2 cores), the
# controller trained, exported, scored; after train-long-milestone STEP=N.
train-long-candidate: $(STAMP)
	STEP=$(STEP) scripts/train_long_candidate.sh $(if $(OUT),$(OUT),runs/long)

# Bundling new weights (scripts/bundle.sh; docs/training.md, "Milestones"): WEIGHTS copied
# over the bundled file, then every report the README, model card and tests read rerun
# with them (resumable; STEPS="stress table2" picks steps); ~2-2.5 h on 2 cores.
.PHONY: bundle
bundle: $(STAMP)
	WEIGHTS=$(WEIGHTS) scripts/bundle.sh

# The paper's Table II protocol, the same six meshes whole under scanner noise and as
# simulated scans with the stress shapes (sota_scan.md), and the DMD-Net vs CNR table,
# written to experiments/results/sota/ (benchmarks/quality/table2.py). WEIGHTS=path (weights file or
# checkpoint directory) adds that DMD-Net as a column next to the bundled one.
sota: $(STAMP)
	$(BIN)/python benchmarks/quality/table2.py --table all --dmd-passes 8 $(if $(WEIGHTS),--weights checkpoint=$(WEIGHTS))

# The paper's ablation studies (experiments/): every study at $(ABLATE_PRESET) (cpu: 29
# rows x 3 seeds of 1000 steps, each row's seeds trained together, sized for <= 3 h on two
# free cores; cpu-offset: the direct-offset head, where the network does the work, 5 seeds,
# about 17 h over several sessions; paper: for a GPU). Reruns skip finished runs and resume interrupted ones;
# results and tables go to experiments/results/$(ABLATE_PRESET)/.
ABLATE_PRESET ?= cpu
ablate: $(STAMP)
	$(BIN)/python -m experiments run --preset $(ABLATE_PRESET)
	$(BIN)/python -m experiments index

# A first look (<= 20 min on two free cores): studies encoding, head, attention and stn
# at 300 steps, 3 seeds, 8 test meshes per split, into experiments/results/cpu-quick/.
ablate-quick: $(STAMP)
	$(BIN)/python -m experiments run --preset cpu-quick
	$(BIN)/python -m experiments index

# Every study at the test preset (2 steps per run), into out/ (also run by the test suite).
# Nearly all of it is compiling: rows that differ only in loss weights (a term switched
# off too), dropout rate or scheme share one train-step program, every phase included;
# rows of one model one init and predictor; rows sharing programs run in one worker (15
# train-step programs and 14 models for 29 rows); the preset's network has one
# aggregator per stream and dense block (no study varies them). 2026-12-06 on 2 idle
# cores (AMD EPYC), cold JAX cache: 2 min 38 s (278 s user, 19 s sys; 224 s of it XLA
# compiles), 1 min 01 s warm (out/ removed, cache kept); with 3 aggregators, 3 min 54 s
# (402 s user). Earlier steps on an Intel Xeon: docs/ablations.md.
ablate-smoke: $(STAMP)
	$(BIN)/python -m experiments run --preset test --out out/ablate-smoke \
		--data-dir out/ablate-smoke-data

# The whole sweep on one GPU (every study, 3 seeds, the paper's schedule scaled to about an
# hour: the gpu preset, dmd_jax/config/presets.py), into experiments/results/gpu/.
ablate-gpu: $(STAMP)
	$(BIN)/python -m experiments run --preset gpu
	$(BIN)/python -m experiments index

# Training steps/s (small, paper) and denoise time at 1M and 10M faces on the device JAX
# sees, into experiments/results/device_bench/ (tiny sizes on CPU; SIZE=full forces the
# real ones, SIZE=tiny shrinks them anywhere).
bench-device: $(STAMP)
	$(BIN)/python -m experiments.device_bench $(if $(SIZE),--size $(SIZE))

# The learned smoothing controller (dmd_jax/controller.py, docs/controller.md): the
# generated set (every noise kind; one search over pre-smoothing x update x passes per
# example; resumable, one process per core; an older search brought to today's by
# --research) into data/smoothing: the even indices below SMOOTHING_EXAMPLES (crops of
# 400-1200 faces; the odd ones too with SMOOTHING_ALL=1) and WHOLE_EXAMPLES whole meshes
# of 2,000-15,000 faces (indices from 10,000: smoothing_set.WHOLE_FROM) and HEAVY_EXAMPLES
# crops under per-coordinate noise of 0.6-3 edges (from 20,000: HEAVY_FROM), then the controller
# trained on it (minutes; chosen on its validation split, reported on its test split) and
# stored beside the bundled network in runs/dmd_controller.msgpack.
SMOOTHING_EXAMPLES ?= 2000
WHOLE_EXAMPLES ?= 1000
HEAVY_EXAMPLES ?= 300
SMALL_SHARDS = $(if $(SMOOTHING_ALL),0/2 1/2,0/4 2/4)
# SMOOTHING_SET=dir NETWORK=weights: the same set searched for another network (a long
# run's milestone: scripts/train_long_candidate.sh).
SMOOTHING_SET ?= data/smoothing
SET_NETWORK = $(if $(NETWORK),--network $(NETWORK))
SEARCH_SET = $(BIN)/python -m dmd_jax.data.smoothing_set --out $(SMOOTHING_SET) $(SET_NETWORK)
.PHONY: controller-data controller controller-oracle
controller-data: $(STAMP)
	$(SEARCH_SET) --examples $(SMOOTHING_EXAMPLES) --shard $(word 1,$(SMALL_SHARDS)) & \
	$(SEARCH_SET) --examples $(SMOOTHING_EXAMPLES) --shard $(word 2,$(SMALL_SHARDS)); wait
	$(SEARCH_SET) --first 10000 --examples $$((10000 + $(WHOLE_EXAMPLES))) --shard 0/2 & \
	$(SEARCH_SET) --first 10000 --examples $$((10000 + $(WHOLE_EXAMPLES))) --shard 1/2; wait
	$(SEARCH_SET) --first 20000 --examples $$((20000 + $(HEAVY_EXAMPLES))) --shard 0/2 & \
	$(SEARCH_SET) --first 20000 --examples $$((20000 + $(HEAVY_EXAMPLES))) --shard 1/2; wait
	$(SEARCH_SET) --research

controller: $(STAMP)
	$(BIN)/python scripts/train_controller.py data/smoothing --out runs/controller.npz \
		--report benchmarks/results/controller.md
	$(BIN)/dmd-jax export-weights dmd_jax/weights/dmd_small.msgpack -o runs/dmd_controller.msgpack \
		--controller runs/controller.npz --overwrite

# The grid oracle on the real validation split (every option per mesh and condition;
# resumable, runs/oracle/) beside the default and the controller's rows of
# benchmarks/results/controller_val.md: benchmarks/results/controller_oracle_val.md.
controller-oracle: $(STAMP)
	$(BIN)/python benchmarks/quality/oracle_val.py
