# logpipe — two commands set everything up on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-stamp
OUT ?= out

SHARED ?= ../shared/data
ETHUCY_SCENES := eth hotel univ zara1 zara2

.PHONY: setup demo test bench lint clean train-ethucy reproduce-ethucy reproduce-apolloscape reproduce-argoverse

# torch first and pinned: a looser pin would pull a multi-GB CUDA build; 2.13.0 is a local CPU wheel here.
$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e '.[dev]'
	touch $(STAMP)

setup: $(STAMP)

demo: setup
	$(VENV)/bin/logpipe ingest tests/data/argoverse1 --out $(OUT)/demo/argoverse1
	$(VENV)/bin/logpipe ingest tests/data/ethucy --out $(OUT)/demo/ethucy
	$(VENV)/bin/logpipe ingest tests/data/apolloscape --out $(OUT)/demo/apolloscape
	@echo "demo outputs in $(OUT)/demo (Parquet shards, samples.parquet, manifest.json, mcap/*.mcap)"

test: setup
	$(PY) -m pytest -q -p no:cacheprovider

bench: setup
	$(PY) -m benchmarks.run --out $(OUT)/bench.json

lint: setup
	$(VENV)/bin/ruff check logpipe stages model tests benchmarks scripts
	$(VENV)/bin/mypy logpipe stages model scripts

# Results files in docs/results/ (tables with the protocol beside every number; see docs/results/README.md).
reproduce-ethucy: setup
	$(PY) scripts/reproduce_ethucy.py

reproduce-apolloscape: setup
	$(PY) scripts/reproduce_apolloscape.py

DATA ?= $(SHARED)/argoverse1/data
MAPS ?= $(SHARED)/argoverse1/maps
reproduce-argoverse: setup
	$(PY) scripts/reproduce_argoverse.py --data $(DATA) --maps $(MAPS)

clean:
	rm -rf $(OUT) .pytest_cache .mypy_cache .ruff_cache

# The five ETH/UCY leave-one-scene-out models shipped in model/checkpoints/ethucy/<scene>/ (two at a time).
train-ethucy: setup
	$(VENV)/bin/logpipe ingest $(SHARED)/ethucy --out $(OUT)/ethucy --no-mcap
	$(MAKE) -j2 $(addprefix train-ethucy-,$(ETHUCY_SCENES))

train-ethucy-%:
	rm -rf $(OUT)/runs/ethucy/$*
	mkdir -p $(OUT)/runs/ethucy
	$(VENV)/bin/logpipe train $(OUT)/ethucy --scene $* --config configs/ethucy.toml --out $(OUT)/runs/ethucy/$* \
		--json > $(OUT)/runs/ethucy/$*.json
	rm -rf model/checkpoints/ethucy/$*
	mkdir -p model/checkpoints/ethucy
	cp -r $(OUT)/runs/ethucy/$*/best model/checkpoints/ethucy/$*
	cp $(OUT)/runs/ethucy/$*.json $(OUT)/runs/ethucy/$*/train_log.jsonl model/checkpoints/ethucy/$*/
