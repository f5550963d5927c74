#!/usr/bin/env bash
# Fill .whl/ (git-ignored: the device tool's run must carry it) with the wheels the GPU
# machine lacks, for Python 3.12 on x86-64 Linux: the project's dependencies beyond JAX, equinox, optimistix,
# lineax, scipy, numba, hypothesis, pytest-xdist, h5py, sympy, rich and wrapt (preinstalled there: KINDS.md of the
# device tool) and the test peers (clifford, kingdon).
# No dependencies are resolved: the list is complete, at the versions the CPU suite is tested with.
# Run it here (with network), then benchmarks/gpu/run_on_device.sh on the device. Usage: download_wheels.sh [DIR]
set -euo pipefail
cd "$(dirname "$0")/../.."
dir=${1:-.whl}
PY=${PY:-python3}
mkdir -p "$dir"
wheels=(
  trimesh==5.2.0 libigl==2.6.3 manifold3d==3.5.4 sksparse-minimal==0.3 tetgen==0.8.4 pyamg==5.4.1
  pygltflib==1.16.5 dataclasses-json==0.6.7 marshmallow==3.26.2 deprecated==1.3.1
  meshio==5.3.5 clifford==1.5.1 sparse==0.19.3 kingdon==3.0.0 traitlets==5.16.1
)
log=$(mktemp)
if ! "$PY" -m pip download --quiet --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux2014_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux_2_27_x86_64 \
  --platform manylinux_2_28_x86_64 --dest "$dir" "${wheels[@]}" > "$log" 2>&1; then
  cat "$log"
  rm -f "$log"
  exit 1
fi
rm -f "$log"
du -sh "$dir"
