# hipode-pipeline: every target makes the virtual environment on first use.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
TORCH_VERSION := 2.13.0
STAMP := $(VENV)/.installed
TASK ?= hopper-m-r
# the learner whose table row stage one builds and stage two trains: td3bc | iql | cql
LEARNER ?= td3bc
# training seeds of `make train`, e.g. 0-4 (one process, one stacked model); empty: seed 0
SEEDS ?=
ARGS ?=
# Torch's worker threads spin on a busy 2-core machine; passive waiting keeps them polite.
export OMP_WAIT_POLICY ?= PASSIVE

.PHONY: setup test collect augment train datasets bench quality sweep lint clean-venv

setup: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	# torch pinned to the CPU build when absent: an unpinned torch pulls gigabytes of CUDA packages
	$(BIN)/python -c "import torch" 2>/dev/null || $(BIN)/pip install -q "torch==$(TORCH_VERSION)"
	$(BIN)/pip install -q -e ".[dev,plots,ray,adroit,report,tensorboard,wandb]"
	touch $(STAMP)

test: $(STAMP)
	$(BIN)/python -m pytest -n 2 --dist loadfile $(ARGS)

collect: $(STAMP)
	$(BIN)/hipode collect $(TASK) $(ARGS)

augment: $(STAMP)
	$(BIN)/hipode augment $(TASK) --learner $(LEARNER) $(ARGS)

train: $(STAMP)
	$(BIN)/hipode train $(TASK) --learner $(LEARNER) $(if $(SEEDS),--seeds $(SEEDS)) $(ARGS)

datasets: $(STAMP)
	$(BIN)/hipode datasets list $(ARGS)

# each benchmark writes its figures, command and machine load to bench/results/
bench: $(STAMP)
	$(BIN)/python bench/collect.py
	$(BIN)/python bench/augment.py
	$(BIN)/python bench/models_precision.py --write
	$(BIN)/python bench/learners.py
	$(BIN)/python bench/verify.py
	$(BIN)/python bench/artifact_io.py

# the quality sweep (hours on a CPU; resumable): make quality ARGS="--tasks hopper-m-r --steps 100000"
quality: $(STAMP)
	$(BIN)/python bench/quality.py $(ARGS)

# any sweep (hipode sweep --help): make sweep ARGS="--tasks hopper-m-r --seeds 0,1,2,3,4"
sweep: $(STAMP)
	$(BIN)/hipode sweep $(ARGS)

lint: $(STAMP)
	$(BIN)/ruff check hipode_pipeline tests bench
	$(BIN)/ruff format --check hipode_pipeline tests bench

clean-venv:
	rm -rf $(VENV)
