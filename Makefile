# Two commands set everything up on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo test test-gpu-variants test-slow test-extended lint docs bench bench-quick bench-compare bench-gpu gpu-programs install clean

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[dev,bench,docs]"
	touch $(STAMP)

install: $(STAMP)

## Run the main job on the built-in default (kernel tour, the rigged arm; figures and a glb in out/).
demo: $(STAMP)
	$(VENV)/bin/jaxcga demo

## Run every test on two workers (pytest-xdist; CI has two cores), except those marked slow and the notebooks.
test: $(STAMP)
	$(PY) -m pytest -n 2 -m "not slow" tests

## The fast tests of the per-platform kernels' callers again, with every kernel's GPU formulation taken on the CPU
## (tests/conftest.py, --gpu-variants): the arithmetic of what a GPU runs, checked without one (CI runs it).
# each kernel's two formulations are compared on its examples in the plain run (tests/shared_layer/
# test_platform_kernels.py); these are their main callers: the sparse solves, skinning (forward kinematics, the
# products, DQS), the FEM and XFEM steps and rollouts, the command line's cache
GPU_VARIANT_TESTS := tests/shared_layer/test_sparse.py tests/shared_layer/test_checks.py tests/deform/test_skinning.py \
	tests/xfem/test_backward_euler.py tests/xfem/test_simulate.py tests/xfem/test_rollout.py tests/cli/test_cache.py
test-gpu-variants: $(STAMP)
	$(PY) -m pytest -n 2 -m "not slow" --gpu-variants $(GPU_VARIANT_TESTS)

## The second CI job: the tests marked slow (benchmark smoke runs, compile-heavy gradient and fitting checks) but
## the extended ones, and the notebooks, executed.
# xfem's slow tests (the character bodies, the largest) run in fresh workers: a worker's memory grows over a run
test-slow: $(STAMP)
	$(PY) -m pytest -n 2 -m "slow and not extended" --durations=10 tests --ignore=tests/xfem
	$(PY) -m pytest -n 2 -m "slow and not extended" --durations=10 tests/xfem
	$(PY) -m pytest -n 2 --nbmake --durations=10 notebooks

## The longest slow tests (tests/extended.txt: corpus-wide sweeps, fuzzing, solver-by-solver equivalences), which
## CI's 90 minutes cannot hold on its 2 cores beside the rest: run them before a release or after changing what they
## cover.
test-extended: $(STAMP)
	$(PY) -m pytest -n 2 -m extended --durations=10 tests --ignore=tests/xfem
	$(PY) -m pytest -n 2 -m extended --durations=10 tests/xfem

## Lint, format and type checks (CI runs them): ruff on the tree, pyright (basic) on the packages, the CLI and the tests.
lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/pyright

## The documentation site into site/ (open site/index.html): mkdocs with --strict, so that a warning (a docstring it
## cannot read, a broken link) fails; the notebooks as stored, the command-line reference from the parsers.
docs: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict --quiet

## Benchmarks: print figures and ratios, write JSON to out/bench/.
bench: $(STAMP)
	mkdir -p out/bench
	$(PY) benchmarks/bench_kernel.py --json out/bench/kernel.json
	$(PY) benchmarks/bench_skinning.py --json out/bench/skinning.json
	$(PY) benchmarks/bench_cutting.py --json out/bench/cutting.json
	$(PY) benchmarks/bench_deform.py --json out/bench/deform.json
	$(PY) benchmarks/bench_arap.py --json out/bench/arap.json
	$(PY) benchmarks/bench_fem.py --json out/bench/fem.json
	$(PY) benchmarks/bench_xfem.py --json out/bench/xfem.json
	$(PY) benchmarks/bench_batch.py --json out/bench/batch.json
	$(PY) benchmarks/bench_viewer.py --json out/bench/viewer.json
	$(PY) benchmarks/bench_cli.py --json out/bench/cli.json

## The quick set: every benchmark, the figures the issues name at their own sizes where those are cheap, the rest
## smaller (benchmarks/quick.py); about 5 minutes on 2 cores, JSON into out/bench-quick/quick.json. ONLY="a b" for some.
bench-quick: $(STAMP)
	$(PY) benchmarks/quick.py --out out/bench-quick $(if $(ONLY),--only $(ONLY))

## The quick set on BASE's packages and on the working tree's, alternately (BASE, tree, BASE, tree: the same load on
## both), measured by the working tree's scripts; then every figure that moved by more than 10%, worse first
## (benchmarks/compare_commit.py, about 4 quick sets). ONLY="skinning kernel" for some benchmarks, ROUNDS=1 for AB.
BASE ?= main
bench-compare: $(STAMP)
	$(PY) benchmarks/compare_commit.py $(BASE) $(if $(ONLY),--only $(ONLY)) $(if $(ROUNDS),--rounds $(ROUNDS))

## Benchmarks on a CUDA GPU: the GPU set at GPU sizes (1e7 points, 100k vertices, FEM 23k, XFEM accordion), names
## suffixed _gpu, JSON to out/bench-gpu/ and the issue 32 targets beside the figures (benchmarks/README.md).
bench-gpu: $(STAMP)
	PY=$(PY) benchmarks/gpu/bench_gpu.sh out/bench-gpu

## The GPU set's programs compiled for an H100 on this machine, no GPU needed: kernel launches, host round trips,
## Triton registers and spills (benchmarks/README.md); the CUDA plugin of the installed jaxlib in .cuda-plugin/.
CUDA_PLUGIN := .cuda-plugin
$(CUDA_PLUGIN)/.installed: $(STAMP)
	version=$$($(PY) -c "import jaxlib; print(jaxlib.__version__)") && \
	$(PY) -m pip install --quiet --no-deps --target $(CUDA_PLUGIN) "jax-cuda13-plugin==$$version" "jax-cuda13-pjrt==$$version"
	touch $@

gpu-programs: $(CUDA_PLUGIN)/.installed
	mkdir -p out
	PYTHONPATH=$(CUDA_PLUGIN) JAX_PLATFORMS=cpu $(PY) benchmarks/gpu/compile_for_gpu.py --json out/gpu-programs.json

clean:
	rm -rf $(VENV) $(CUDA_PLUGIN) out .pytest_cache site .cache
