#!/usr/bin/env bash
# The GPU benchmark set at GPU sizes (`make bench-gpu`, benchmarks/README.md "On a GPU"): JSON into the folder $1
# (default out/bench-gpu), every name suffixed _gpu, then the issue 32 targets against them (summary.py).
# PY: the Python (default python3). LIMIT: seconds each benchmark may take; DEADLINE: a time (seconds since the
# epoch) by which all must end (both default: none). A benchmark that fails or runs out does not stop the others;
# the exit status is the number that did.
set -u
cd "$(dirname "$0")/../.."
out=${1:-out/bench-gpu}
py=${PY:-python3}
export JAX_PLATFORMS=${JAX_PLATFORMS:-cuda}  # the GPU set: on a machine without one it fails rather than run on the CPU
mkdir -p "$out"
failed=0

bench() {  # bench NAME ARGS...: benchmarks/bench_NAME.py ARGS --json $out/NAME.json, within LIMIT and DEADLINE
  local name=$1 limit=${LIMIT:-0} start=$SECONDS
  shift
  if [ -n "${DEADLINE:-}" ]; then
    local left=$((DEADLINE - $(date +%s)))
    if [ "$left" -lt 20 ]; then echo "== $name: skipped, no time left"; failed=$((failed + 1)); return; fi
    if [ "$limit" -eq 0 ] || [ "$limit" -gt "$left" ]; then limit=$left; fi
  fi
  echo "== $name: $* (limit ${limit} s; 0: none)"
  if timeout -k 10 "$limit" "$py" "benchmarks/bench_$name.py" "$@" --json "$out/$name.json"; then
    echo "== $name: done in $((SECONDS - start)) s"
  else
    echo "== $name: FAILED (exit $?) after $((SECONDS - start)) s"
    failed=$((failed + 1))
  fi
}

# the figures of issue 32, item 5, cheapest first; repetitions kept low (medians of few calls)
bench kernel --points 10000000 --repeats 5 --tune-rows
bench skinning --vertices 100000 --poses 1000 --repeats 20 --batch-repeats 2
bench deform --vertices 100000 --repeats 5 --harmonic-repeats 2
bench arap --vertices 100000 --iterations 10 --repeats 2
bench fem --sizes 23k --steps 3
bench xfem --scenes accordion --figures table --no-background --steps 155
"$py" benchmarks/gpu/summary.py "$out"
exit "$failed"
