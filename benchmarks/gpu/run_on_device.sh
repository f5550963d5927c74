#!/usr/bin/env bash
# Issue 32's GPU check in one go on the device machine (Python 3.12, JAX with CUDA, equinox, optimistix, lineax,
# scipy, numba and hypothesis preinstalled): install the wheels of .whl/ (benchmarks/gpu/download_wheels.sh, run
# here first; the device tool must carry .whl) into /tmp/site, run the fast tests on the GPU, then the GPU
# benchmark set (bench_gpu.sh). Logs, junit XML, JSON and summary.txt go to $OUT (default out/device).
#   benchmarks/gpu/run_on_device.sh [all|tests|bench]
# TOTAL_SECONDS (default 570: the device tool stops a command at 600 s) bounds the whole run, TEST_SECONDS
# (default 250; 1,130 of the suite's tests took 185 s on 15 workers on an H100) the tests on TEST_WORKERS (default 15)
# workers (TEST_PATHS: default tests); the benchmarks get the rest, each stopped at the deadline (xfem, the
# longest, last).
set -uo pipefail
cd "$(dirname "$0")/../.."
part=${1:-all}
out=${OUT:-out/device}
mkdir -p "$out"
deadline=$(($(date +%s) + ${TOTAL_SECONDS:-570}))
summary=$out/summary.txt
: > "$summary"
say() { echo "$*" | tee -a "$summary"; }

site=/tmp/site
if ! python3 -m pip install --quiet --no-index --no-deps --target "$site" .whl/*.whl > "$out/install.log" 2>&1; then
  say "pip install from .whl failed: see install.log"
fi
# the project itself, for its distribution metadata (the version test); the source tree stays first on the path
if ! python3 -m pip install --quiet --no-index --no-deps --no-build-isolation --target "$site/project" . \
  >> "$out/install.log" 2>&1; then
  say "pip install of the project failed: see install.log"
fi
# kingdon imports anywidget (Jupyter widgets) at import time; its widgets are never used here
mkdir -p "$site/anywidget"
printf 'class AnyWidget:\n    pass\n' > "$site/anywidget/__init__.py"
export PYTHONPATH=$PWD:$site:$site/project
export XLA_PYTHON_CLIENT_PREALLOCATE=false JAX_PLATFORMS=${JAX_PLATFORMS:-cuda}
say "$(nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>&1 | head -1)"
say "$(python3 -c 'import sys, jax; print("python", sys.version.split()[0], "jax", jax.__version__, "default backend",
  jax.default_backend(), jax.devices()[0].device_kind)' 2>&1 | tail -1)"
say "$(python3 -c 'import importlib
names = ("jax equinox optimistix optax lineax jaxtyping numpy scipy numba trimesh igl manifold3d sksparse_minimal "
         "pygltflib tqdm matplotlib tetgen meshio pytest hypothesis xdist clifford kingdon").split()
missing = []
for name in names:
    try:
        importlib.import_module(name)
    except Exception as error:
        missing.append(f"{name} ({type(error).__name__}: {error})")
print("modules missing: " + ("; ".join(missing) if missing else "none"))' 2>&1 | tail -1)"

if [ "$part" = all ] || [ "$part" = tests ]; then
  start=$SECONDS
  # SIGINT at the limit: pytest stops, reports what ran and writes the junit XML
  # shellcheck disable=SC2086  # TEST_PATHS: paths, split
  timeout -s INT -k 30 "${TEST_SECONDS:-250}" python3 -m pytest -n "${TEST_WORKERS:-15}" -m "not slow" \
    -p no:cacheprovider -v -rfEs --durations=25 --junitxml="$out/junit.xml" ${TEST_PATHS:-tests} > "$out/tests.log" 2>&1
  rc=$?
  say "tests: exit $rc after $((SECONDS - start)) s (124/130: stopped at the limit): $(grep -E '(passed|failed|error)' \
    "$out/tests.log" | tail -1)"
  # -v streams each result ("[gw3] FAILED tests/..."): an interrupted run whose summary is lost still names them
  grep -E '^(FAILED|ERROR|SKIPPED)|\] (FAILED|ERROR) ' "$out/tests.log" | sort -u | tee -a "$summary"
fi

if [ "$part" = all ] || [ "$part" = bench ]; then
  PY=python3 DEADLINE=$((deadline - 5)) benchmarks/gpu/bench_gpu.sh "$out/bench-gpu" > "$out/bench.log" 2>&1
  say "benchmarks: $? failed or stopped (bench.log)"
  grep '^== ' "$out/bench.log" | tee -a "$summary"
  python3 benchmarks/gpu/summary.py "$out/bench-gpu" | tee -a "$summary"
  # the device tool returns at most 8 files: the JSON files travel as one archive
  tar czf "$out/bench-gpu.tgz" -C "$out" bench-gpu && rm -r "$out/bench-gpu"
fi
