# logpipe — two commands set everything up on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-stamp
OUT ?= out

SHARED ?= ../shared/data
ETHUCY_SCENES := eth hotel univ zara1 zara2

.PHONY: setup demo test bench lint clean train-driving train-ethucy train-ethucy-social train-apolloscape train-ethucy-paper train-apolloscape-paper reproduce-ethucy reproduce-apolloscape reproduce-argoverse reproduce-driving replica-cost scaling fuzz synthetic-map-check synthetic-pretrain

# torch first and pinned: a looser pin would pull a multi-GB CUDA build; 2.13.0 is a local CPU wheel here.
# The installers' output goes to $(INSTALL_LOG), named (and its end shown) only when a step fails.
INSTALL_LOG := $(VENV).install.log
$(STAMP): pyproject.toml
	@echo "setup: creating $(VENV) and installing logpipe with its test tools (a few minutes the first time; log: $(INSTALL_LOG))"
	@( $(PYTHON) -m venv $(VENV) && $(PY) -m pip install -q --upgrade pip \
	  && $(PY) -m pip install -q torch==2.13.0 && $(PY) -m pip install -q -e '.[dev]' ) > $(INSTALL_LOG) 2>&1 \
	  || { tail -n 20 $(INSTALL_LOG); echo "setup failed: the whole log is $(INSTALL_LOG)"; exit 1; }
	@touch $(STAMP)
	@echo "setup: done ($(VENV)/bin/logpipe; source $(VENV)/bin/activate to type plain logpipe)"

setup: $(STAMP)

LP := $(VENV)/bin/logpipe
DEMO := $(OUT)/demo
M := tests/data/maps
DRV := tests/data/driving

# Every stage on the bundled samples (tests/data): two Argoverse 1 sequences held out from the shipped driving
# model (hash/test) with their map crops, predicted by that model over their lane rasters; ETH/UCY with the
# shipped checkpoint for the held-out ETH scene; ApolloScape with its shipped checkpoint. Each step prints one
# line (the commands run with -q); the scores, then the picture and the MCAP to open, close it.
DEMO_LP := $(LP) -q
demo: setup
	@rm -rf $(DEMO)
	@echo "demo 1/5: Argoverse 1: ingest two logs, rasterise their lane maps, predict with the driving model"
	@$(DEMO_LP) ingest $(DRV)/20.csv $(DRV)/32.csv --out $(DEMO)/argoverse1
	@$(DEMO_LP) rasterise $(DEMO)/argoverse1 --map MIA=$(DRV)/MIA_lane_centerlines_crop_20.npz \
		--map PIT=$(DRV)/PIT_lane_centerlines_crop_32.npz --rotate --preview 2
	@$(DEMO_LP) predict $(DEMO)/argoverse1 --out $(DEMO)/predict-argoverse1
	@echo "demo 2/5: Argoverse 1: score"
	@$(LP) score $(DEMO)/predict-argoverse1 --truth $(DEMO)/argoverse1 --agents focal \
		--out $(DEMO)/score-argoverse1
	@echo "demo 3/5: ETH/UCY: ingest, predict the held-out ETH scene, score"
	@$(DEMO_LP) ingest tests/data/ethucy --out $(DEMO)/ethucy
	@$(DEMO_LP) predict $(DEMO)/ethucy --filter split=eth/test --out $(DEMO)/predict-ethucy
	@$(LP) score $(DEMO)/predict-ethucy --truth $(DEMO)/ethucy --split eth/test \
		--out $(DEMO)/score-ethucy
	@echo "demo 4/5: ApolloScape: ingest, predict"
	@$(DEMO_LP) ingest tests/data/apolloscape --out $(DEMO)/apolloscape
	@$(DEMO_LP) predict $(DEMO)/apolloscape --out $(DEMO)/predict-apolloscape
	@echo "demo 5/5: the picture of a forecast over its raster, and Rerun recordings"
	@$(PY) -m logpipe.scoring.forecast_picture $(DEMO)/predict-argoverse1 --truth $(DEMO)/argoverse1 \
		--out $(DEMO)/forecast.png > /dev/null
	@$(DEMO_LP) export $(DEMO)/predict-argoverse1 --format rrd --out $(DEMO)/rrd
	@echo "demo done, outputs in $(DEMO)/. Open:"
	@echo "  picture: $(DEMO)/forecast.png   (a forecast over its lane raster)"
	@echo "  MCAP:    $(DEMO)/predict-argoverse1/mcap/part-00000/20.mcap   (Foxglove: File > Open local file, 3D panel)"
	@echo "  Rerun:   $(VENV)/bin/rerun $(DEMO)/rrd/20.rrd"
	@echo "  report:  $(DEMO)/score-argoverse1/report.md"

# The full suite; its last line says how long it took on this machine (make setup aside).
# pytest-xdist: most tests are single-threaded Python and many wait on subprocesses (crash injection, Ray, the
# README run), so 3 workers keep 2 cores busy. Measured on 2 cores (AMD EPYC, AVX-512), 2026-12-07: the suite
# costs ~640 s of CPU in all (processes it starts and Ray's included) and takes 330-350 s; a fresh clone adds
# ~75 s of set-up. The suite starts ~300 Python processes: it lets Python keep compiled modules
# (__pycache__, git-ignored) even where PYTHONDONTWRITEBYTECODE is set, so each does not compile logpipe anew.
# Override the worker count with make test TEST_WORKERS=N.
TEST_WORKERS ?= 3
test: setup
	@echo "test: the full suite on $(TEST_WORKERS) workers (about 5.5 minutes on 2 cores, plus ~1.5 for the first set-up; its last line says how long it took); progress dots below, failures at the end"
	@start=$$(date +%s); env -u PYTHONDONTWRITEBYTECODE $(PY) -m pytest -q -p no:cacheprovider -n $(TEST_WORKERS) \
	  --dist worksteal; rc=$$?; \
	  echo "test: took $$(( $$(date +%s) - start )) s"; exit $$rc

bench: setup
	$(PY) -m benchmarks.run --out $(OUT)/bench.json --markdown $(OUT)/bench.md

# mypy cannot follow the editable install's mapping of model/ and stages/ to logpipe.model / logpipe.stages (it
# typed them Any), so it reads the package from a tree of links laid out as installed.
lint: setup
	$(VENV)/bin/ruff check logpipe stages model tests benchmarks scripts
	rm -rf .mypy-tree && mkdir -p .mypy-tree/logpipe
	for f in logpipe/*; do ln -s ../../$$f .mypy-tree/logpipe/; done
	ln -s ../../model .mypy-tree/logpipe/model && ln -s ../../stages .mypy-tree/logpipe/stages
	MYPYPATH=.mypy-tree:. $(VENV)/bin/mypy -p logpipe -p scripts -p benchmarks

# Results files in docs/results/ (tables with the protocol beside every number; see docs/results/README.md).
reproduce-ethucy: setup
	$(PY) -m scripts.reproduce_ethucy --seeds-dir $(OUT)/checkpoints

reproduce-apolloscape: setup
	$(PY) -m scripts.reproduce_apolloscape --seeds-dir $(OUT)/checkpoints

DATA ?= $(SHARED)/argoverse1/data
MAPS ?= $(SHARED)/argoverse1/maps
reproduce-argoverse: setup
	$(PY) -m scripts.reproduce_argoverse --data $(DATA) --maps $(MAPS)

# Every stage timed on a 2,000-sequence AV1 replica; the projected cost of the full Argoverse sets
# (docs/results/argoverse_cost.md, embedded in argoverse.md by reproduce-argoverse). About 6 minutes.
replica-cost: setup
	$(PY) -m scripts.replica_cost

# ingest → rasterise → predict on a 50,000-log AV1 replica, locally and on Ray with 1 and 2 workers (docs/scaling.md).
# Three rounds (medians reported), about an hour, and ~25 GB of scratch space in out/scaling (removed at the end).
scaling: setup
	$(PY) -m scripts.scaling

# The driving model on the real AV1 + AV2 logs (docs/results/argoverse_logs.md): trains what is missing (resumable),
# then scores hash/test.
reproduce-driving: setup
	$(PY) -m scripts.reproduce_driving

clean:
	rm -rf $(OUT) .pytest_cache .mypy_cache .ruff_cache .mypy-tree

# Shipped checkpoints, two trainings at a time: the paper's method (zhu2020) and the LSTM / Noise-LSTM baselines,
# trained with the same config (`--preset` swaps only the features and noise). ETH/UCY: one per left-out scene in
# model/checkpoints/ethucy/<scene>/ (baselines in its lstm/ and noise_lstm/); ApolloScape: model/checkpoints/apolloscape/<method>.
# SEED=N (N > 0) trains the same runs with train.seed = N into $(OUT)/checkpoints/seedN/, outside the package (the
# reproduce scripts' across-seeds tables read every seedN/ there: their --seeds-dir).
LEARNED_METHODS := zhu2020 noise_lstm lstm
# ETH/UCY also trains the paper's method without its position feature (eqs. 1-2), an ablation row of its table.
ETHUCY_METHODS := $(LEARNED_METHODS) no_position
SEED ?= 0
CKPT := $(if $(filter 0,$(SEED)),model/checkpoints,$(OUT)/checkpoints/seed$(SEED))
RUNS := $(OUT)/runs$(if $(filter 0,$(SEED)),,/seed$(SEED))
preset_flag = $(if $(filter noise_lstm,$(1)),--preset baseline,$(if $(filter lstm no_position,$(1)),--preset $(1),))
# copy_best(run, dest): replace only the files of the checkpoint in dest, so baselines nested in it survive.
copy_best = mkdir -p $(2) && find $(2) -maxdepth 1 -type f -delete && cp $(1)/best/* $(1)/train_log.jsonl $(2)/ \
	&& cp $(1).json $(2)/train_summary.json

# predict's default for Argoverse 1, AV2 and CommonRoad data (model/checkpoints/argoverse/residual): the residual
# model trained on hash/train of all six real locations (scripts/driving_targets.py builds the same datasets for
# the leave-one-location-out run, `python -m scripts.driving_lolo`); ~0.3 core-hours.
DRIVING := $(OUT)/driving_residual
train-driving: setup
	$(LP) -q ingest $(SHARED)/argoverse1/data --out $(DRIVING)/av1 --protocol argoverse \
		--targets fully_observed_no_ego --no-mcap
	$(LP) -q ingest $(SHARED)/av2 --out $(DRIVING)/av2 --protocol argoverse2 --obs 20 --pred 30 --window sliding \
		--stride 10 --targets fully_observed_no_ego --target-types vehicle,bus_truck --no-mcap
	$(LP) -q ingest $(SHARED)/commonroad/ngsim --out $(DRIVING)/ngsim --no-mcap
	$(LP) -q rasterise $(DRIVING)/av1 --maps $(SHARED)/argoverse1/maps --rotate
	$(LP) -q rasterise $(DRIVING)/av2 --maps $(SHARED)/av2 --rotate
	$(LP) -q rasterise $(DRIVING)/ngsim --rotate
	$(LP) train $(DRIVING)/av1 $(DRIVING)/av2 $(DRIVING)/ngsim --config configs/driving_residual.toml \
		--train-split hash/train --val-split hash/val --out $(OUT)/checkpoints/argoverse/residual

train-ethucy: setup
	$(VENV)/bin/logpipe ingest $(SHARED)/ethucy --out $(OUT)/ethucy --no-mcap
	$(MAKE) -j2 $(foreach m,$(ETHUCY_METHODS),$(addprefix train-ethucy/$(m)/,$(ETHUCY_SCENES)))

train-ethucy/%:
	$(eval method := $(word 1,$(subst /, ,$*)))
	$(eval scene := $(word 2,$(subst /, ,$*)))
	rm -rf $(RUNS)/ethucy/$*
	mkdir -p $(RUNS)/ethucy/$(method)
	$(VENV)/bin/logpipe train $(OUT)/ethucy --scene $(scene) --config configs/ethucy.toml $(call preset_flag,$(method)) \
		--seed $(SEED) --out $(RUNS)/ethucy/$* --json > $(RUNS)/ethucy/$*.json
	$(call copy_best,$(RUNS)/ethucy/$*,$(CKPT)/ethucy/$(scene)$(if $(filter zhu2020,$(method)),,/$(method)))

# The social baselines (issue 63; model/social_lstm, model/social_gan): Social-LSTM, Social-GAN 20V-20 and 20VP-20 for
# each left-out scene, ONE training at a time (each is single-threaded: OMP_NUM_THREADS=1), then predict + score of
# S/test (Social-GAN's windows, --min-agents 2; K = 20, and K = 1 for Social-LSTM's mean). Runs in
# $(RUNS)/ethucy-social/<scene>/<preset>, scores beside them. SOCIAL_CONFIG: the published schedule by default
# (20,000 iterations, early stopping on S/val); configs/ethucy_social_budget.toml (round one) and
# configs/ethucy_social_round2.toml stop each run on a time budget. A run stopped early goes on with
# `logpipe train ... --resume` into the same folder (this target starts every run afresh).
SOCIAL_PRESETS := social_lstm social_gan_20v social_gan_20vp
SOCIAL_CONFIG ?=
SOCIAL := $(RUNS)/ethucy-social
train-ethucy-social: setup
	$(LP) -q ingest $(SHARED)/ethucy --out $(OUT)/ethucy --no-mcap
	for scene in $(ETHUCY_SCENES); do for preset in $(SOCIAL_PRESETS); do \
		run=$(SOCIAL)/$$scene/$$preset; rm -rf $$run; mkdir -p $(SOCIAL)/$$scene || exit 1; \
		OMP_NUM_THREADS=1 $(LP) train $(OUT)/ethucy --scene $$scene --preset $$preset \
			$(if $(SOCIAL_CONFIG),--config $(SOCIAL_CONFIG),) --seed $(SEED) --out $$run --json > $$run.json || exit 1; \
		$(LP) -q predict $(OUT)/ethucy --checkpoint $$run/best --filter split=$$scene/test --out $$run-pred \
			--no-mcap || exit 1; \
		$(LP) score $$run-pred --truth $(OUT)/ethucy --split $$scene/test --min-agents 2 --no-plots \
			--out $$run-score --json > $$run-score.json || exit 1; \
		if [ $$preset = social_lstm ]; then \
			$(LP) -q predict $(OUT)/ethucy --checkpoint $$run/best --filter split=$$scene/test --modes 1 \
				--out $$run-pred-k1 --no-mcap && $(LP) score $$run-pred-k1 --truth $(OUT)/ethucy \
				--split $$scene/test --min-agents 2 --no-plots --out $$run-score-k1 --json > $$run-score-k1.json \
				|| exit 1; fi; \
	done; done

# The paper's method as the paper specifies it (configs/*_paper.toml: model defaults, eq. 23's per-scene loss), the
# rows the results tables lead with: model/checkpoints/ethucy/<scene>/paper and model/checkpoints/apolloscape/paper.
train-ethucy-paper: setup
	$(VENV)/bin/logpipe ingest $(SHARED)/ethucy --out $(OUT)/ethucy --no-mcap
	$(MAKE) -j2 $(addprefix train-ethucy-paper/,$(ETHUCY_SCENES))

train-ethucy-paper/%:
	rm -rf $(RUNS)/ethucy/paper/$*
	mkdir -p $(RUNS)/ethucy/paper
	$(VENV)/bin/logpipe train $(OUT)/ethucy --scene $* --config configs/ethucy_paper.toml --seed $(SEED) \
		--out $(RUNS)/ethucy/paper/$* --json > $(RUNS)/ethucy/paper/$*.json
	$(call copy_best,$(RUNS)/ethucy/paper/$*,$(CKPT)/ethucy/$*/paper)

train-apolloscape-paper: setup
	$(VENV)/bin/logpipe ingest $(SHARED)/apolloscape/prediction_train --format apolloscape \
		--out $(OUT)/reproduce/apolloscape/dataset --no-mcap
	rm -rf $(RUNS)/apolloscape/paper
	mkdir -p $(RUNS)/apolloscape
	$(VENV)/bin/logpipe train $(OUT)/reproduce/apolloscape/dataset --train-split hash/train --val-split hash/val \
		--config configs/apolloscape_paper.toml --seed $(SEED) --out $(RUNS)/apolloscape/paper \
		--json > $(RUNS)/apolloscape/paper.json
	$(call copy_best,$(RUNS)/apolloscape/paper,$(CKPT)/apolloscape/paper)

train-apolloscape: setup
	$(VENV)/bin/logpipe ingest $(SHARED)/apolloscape/prediction_train --format apolloscape \
		--out $(OUT)/reproduce/apolloscape/dataset --no-mcap
	$(MAKE) -j2 $(addprefix train-apolloscape/,$(LEARNED_METHODS))

train-apolloscape/%:
	rm -rf $(RUNS)/apolloscape/$*
	mkdir -p $(RUNS)/apolloscape
	$(VENV)/bin/logpipe train $(OUT)/reproduce/apolloscape/dataset --train-split hash/train --val-split hash/val \
		--config configs/apolloscape.toml $(call preset_flag,$*) --seed $(SEED) --out $(RUNS)/apolloscape/$* \
		--json > $(RUNS)/apolloscape/$*.json
	$(call copy_best,$(RUNS)/apolloscape/$*,$(CKPT)/apolloscape/$*)

# The damaged-input corpus (tests/fuzz/corpus.py, ~1,130 cases over every format and the map files; the
# ../shared ones are skipped when it is absent): figures in $(OUT)/fuzz.json. A fast subset runs in `make test`.
# Then the crash injection with 20 random-time kills per stage (make test runs 6).
fuzz: setup
	OUT=$(OUT) $(PY) -m pytest -q -p no:cacheprovider tests/fuzz -m fuzz
	LOGPIPE_RANDOM_KILLS=20 $(PY) -m pytest -q -p no:cacheprovider tests/integration/test_crash_injection.py

# SYNTHETIC map check (docs/results/argoverse_synthetic.md): does the environment net read the lanes? Traffic
# simulated on the real Argoverse 1 lane graphs (logpipe.synthetic.traffic), a held-out region per city for test,
# the full model and v4 (no EN) trained alike (configs/argoverse_synthetic.toml), scored on the held-out windows.
# ~3 h on 2 cores (the full model's environment net is ~3/4 of it). SYN_WINDOWS / SYN_STEPS shrink it.
SYN_WINDOWS ?= 20000
SYN_STEPS ?= 1500
SYN := $(OUT)/synthetic
AV1_MAPS := $(SHARED)/argoverse1/maps
synthetic-map-check: setup
	$(PY) -m logpipe.synthetic.traffic --maps $(AV1_MAPS) --out $(SYN)/csv --windows $(SYN_WINDOWS) --seed 0
	for part in train test; do \
		$(LP) ingest $(SYN)/csv/$$part --out $(SYN)/$$part --protocol argoverse --targets fully_observed_no_ego \
			--no-mcap && $(LP) rasterise $(SYN)/$$part --maps $(AV1_MAPS) --rotate || exit 1; done
	$(MAKE) -j2 $(SYN)/runs/full $(SYN)/runs/v4
	$(PY) -m scripts.synthetic_map_check --full $(SYN)/runs/full --no-en $(SYN)/runs/v4 --test $(SYN)/test

$(SYN)/runs/%:
	mkdir -p $(SYN)/runs && OMP_NUM_THREADS=1 $(LP) train $(SYN)/train --train-split hash/train --val-split hash/val \
		--config configs/argoverse_synthetic.toml --preset $* --steps $(SYN_STEPS) --out $@ --json > $@.json

# SYNTHETIC pre-training traffic (issue 57 item 2; docs/synthetic.md): 210,000 windows of simulated traffic on every
# real lane graph held (NGSIM US-101 / Lankershim / Peachtree lanelets, AV2 log maps, AV1 MIA / PIT centerlines), on
# one core; re-running resumes (finished scenes are skipped, ingest skips ingested files). Ingested whole into
# $(PRETRAIN)/commonroad and $(PRETRAIN)/av1; rasters (343 KiB a window at the real 7 x 224 x 224 spec, 70 GB for all)
# for every 10th scene only, ingested apart into $(PRETRAIN)/commonroad_r and $(PRETRAIN)/av1_r.
PRETRAIN := $(OUT)/synthetic57
PRETRAIN_SCALE ?= 1
ONE_CORE := OMP_NUM_THREADS=1 nice -n 10
synthetic-pretrain: setup
	$(ONE_CORE) $(PY) -m logpipe.synthetic.pretrain --shared $(SHARED) --out $(PRETRAIN)/data --seed 0 --scale $(PRETRAIN_SCALE)
	$(ONE_CORE) $(LP) ingest $(PRETRAIN)/data/commonroad --out $(PRETRAIN)/commonroad --no-mcap --workers 1
	$(ONE_CORE) $(LP) ingest $(PRETRAIN)/data/av1 --out $(PRETRAIN)/av1 --protocol argoverse --targets fully_observed_no_ego \
		--no-mcap --workers 1
	rm -rf $(PRETRAIN)/subset && mkdir -p $(PRETRAIN)/subset/commonroad $(PRETRAIN)/subset/av1
	find $(PRETRAIN)/data/commonroad -name 'synthetic_*0.xml.gz' -exec ln -f {} $(PRETRAIN)/subset/commonroad/ \;
	find $(PRETRAIN)/data/av1 -name 'synthetic_*0_[0-9][0-9].csv' -exec ln -f {} $(PRETRAIN)/subset/av1/ \;
	$(ONE_CORE) $(LP) ingest $(PRETRAIN)/subset/commonroad --out $(PRETRAIN)/commonroad_r --no-mcap --workers 1
	$(ONE_CORE) $(LP) ingest $(PRETRAIN)/subset/av1 --out $(PRETRAIN)/av1_r --protocol argoverse \
		--targets fully_observed_no_ego --no-mcap --workers 1
	$(ONE_CORE) $(LP) rasterise $(PRETRAIN)/commonroad_r --rotate
	$(ONE_CORE) $(LP) rasterise $(PRETRAIN)/av1_r --maps $(AV1_MAPS) --rotate
