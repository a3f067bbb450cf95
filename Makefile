# swarmmap: `make run` sets up and runs the demo, `make test` sets up and runs the tests (unit and
# end to end), `make test-unit` the unit tests alone (minutes, no process or socket), `make test-deploy` the deploy tier (real Docker engine and SLURM cluster, set up
# from ../shared/kit; needs root), `make test-faults` the fault trials (learners killed at random rounds),
# `make test-network` a team across network namespaces (routers killed, links cut; needs root).
PYTHON ?= python3
VENV ?= .venv
# The torch build to install when the venv has none (CPU-only machines: the 2.13.0 CPU wheel;
# `make setup TORCH=torch` takes whatever PyPI offers, e.g. a CUDA build).
TORCH ?= torch==2.13.0
BIN := $(VENV)/bin
RUN_ARGS ?=

.PHONY: setup run test test-unit test-deploy test-faults test-network clean

$(BIN)/swarmmap: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -c "import torch" 2>/dev/null || $(BIN)/pip install --quiet $(TORCH)
	$(BIN)/pip install --quiet -e '.[test,ros2]'
	@touch $@

setup: $(BIN)/swarmmap

run: setup
	$(BIN)/swarmmap up --preset demo $(RUN_ARGS)

test: setup
	$(BIN)/python -m pytest -ra --durations=15 -m "not deploy and not faults and not network"

# The fast tier: no process started, no socket opened (tests/conftest.py stops a test that tries).
test-unit: setup
	SWARMMAP_TEST_TIER=unit $(BIN)/python -m pytest -ra -q -m "not e2e and not integration and not deploy and not faults and not network"

test-faults: setup
	$(BIN)/python -m pytest -ra -m faults

test-network: setup
	@command -v nft >/dev/null || [ "$$(id -u)" != 0 ] || ! command -v apt-get >/dev/null || \
	  (echo "installing nftables (the network tier's packet loss and partitions)"; apt-get update -qq && \
	   DEBIAN_FRONTEND=noninteractive apt-get install -y -qq nftables >/dev/null)
	$(BIN)/python -m pytest -ra -m network tests/network

test-deploy: setup
	$(BIN)/python -m pytest -ra -m deploy tests/deploy

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
