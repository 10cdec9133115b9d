#!/usr/bin/env bash
# The GPU checks, on a machine with an NVIDIA GPU: build, run every test
# suite labelled gpu on the hardware EGL device (never llvmpipe), then the
# GPU benchmarks in their quick settings, and print their tables. The whole
# run keeps to a time budget (default 540 s): a step that would start
# after the budget is spent is skipped and named, so the script always
# ends with a summary.
#
#   tests/bench/gpu-check.sh [--build DIR | --bundle DIR] [--budget-s S] [--scenes DIR] [--out DIR]
#
# --build DIR   a build folder to reuse (configured here when it has no
#               CMakeCache.txt); default build-gpu
# --bundle DIR  run what gpu-bundle.sh packed elsewhere (a folder or its
#               .tar.gz) instead of building: for a machine with the NVIDIA
#               driver but without Debian's development packages. The scenes
#               default to the bundle's.
# --scenes DIR  the shared real scenes (default $VISQ_SHARED_SCENES, then
#               ../shared/scenes); benchmarks that need them say so and skip
# --out DIR     where each step's full output goes (default $OUT when set,
#               else build-gpu/gpu-check)
#
# Exit status: 0 when every step that ran passed, 1 when one failed, 77 when
# the machine has no hardware EGL device (nothing here can be checked).
set -u -o pipefail

root="$(cd "$(dirname "$0")/../.." && pwd)"
build="$root/build-gpu"
bundle=""
budget_s=540
scenes="${VISQ_SHARED_SCENES:-$root/../shared/scenes}"
scenes_given=0
out="${OUT:-}"
while [ $# -gt 0 ]; do
  case "$1" in
    --build) build="$(realpath -m "$2")"; shift 2 ;;
    --bundle) bundle="$(realpath -m "$2")"; shift 2 ;;
    --budget-s) budget_s="$2"; shift 2 ;;
    --scenes) scenes="$(realpath -m "$2")"; scenes_given=1; shift 2 ;;
    --out) out="$(realpath -m "$2")"; shift 2 ;;
    *) echo "usage: $0 [--build DIR | --bundle DIR] [--budget-s S] [--scenes DIR] [--out DIR]" >&2; exit 2 ;;
  esac
done
[ -n "$out" ] || out="$build/gpu-check"
mkdir -p "$out"
start=$(date +%s)
summary=()
failed=0

elapsed() { echo $(( $(date +%s) - start )); }
left() { echo $(( budget_s - $(elapsed) )); }

# step NAME MIN_SECONDS COMMAND...: runs COMMAND with what is left of the
# budget as its timeout, its output to the terminal and to $out/NAME.log.
step() {
  local name="$1" need="$2"; shift 2
  local remaining; remaining=$(left)
  if [ "$remaining" -lt "$need" ]; then
    summary+=("$(printf '%-28s skipped: %ss of the budget left, it needs about %ss' "$name" "$remaining" "$need")")
    return 0
  fi
  echo "=== $name (budget left ${remaining}s)"
  local t0; t0=$(date +%s)
  # Line-buffered, so a step stopped at the budget still shows how far it got.
  timeout --signal=TERM --kill-after=10 "$remaining" stdbuf -oL "$@" 2>&1 | tee "$out/$name.log"
  local rc=${PIPESTATUS[0]}
  local took=$(( $(date +%s) - t0 ))
  if [ "$rc" -eq 0 ]; then
    summary+=("$(printf '%-28s passed in %ss' "$name" "$took")")
  elif [ "$rc" -eq 124 ] || [ "$rc" -eq 137 ]; then
    summary+=("$(printf '%-28s stopped at the budget after %ss' "$name" "$took")")
    failed=1
  else
    summary+=("$(printf '%-28s FAILED (exit %s) after %ss, see %s' "$name" "$rc" "$took" "$out/$name.log")")
    failed=1
  fi
}

finish() {
  echo
  echo "=== gpu-check summary ($(elapsed)s of ${budget_s}s; logs in $out)"
  for line in "${summary[@]}"; do echo "  $line"; done
  exit "$failed"
}

tools=(cmake c++ nvidia-smi)
[ -z "$bundle" ] || tools=(nvidia-smi)
for tool in "${tools[@]}"; do
  if ! command -v "$tool" > /dev/null; then
    if [ "$tool" = nvidia-smi ]; then
      echo "gpu-check: no nvidia-smi: this is not an NVIDIA machine, nothing to check"
      exit 77
    fi
    echo "gpu-check: $tool is missing: run deploy/install-deps.sh build first" >&2
    exit 1
  fi
done
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader | sed 's/^/gpu-check: GPU: /'

# "auto" takes only a hardware EGL device and fails otherwise, so every
# figure below is the GPU's, never llvmpipe's.
export VISQ_EGL_DEVICE=auto
export VISQ_SHARED_SCENES="$scenes"

if [ -n "$bundle" ]; then
  if [[ "$bundle" == *.tar.gz ]]; then
    mkdir -p "$build" && tar -C "$build" -xzf "$bundle" && bundle="$build/gpu-bundle" || exit 1
  fi
  [ -f "$bundle/suites.txt" ] || { echo "gpu-check: $bundle is not a gpu-bundle.sh folder" >&2; exit 1; }
  echo "gpu-check: bundle of commit $(cat "$bundle/commit.txt" 2> /dev/null || echo unknown)"
  [ "$scenes_given" -eq 1 ] || scenes="$bundle/scenes"
  export VISQ_SHARED_SCENES="$scenes"
  export LD_LIBRARY_PATH="$bundle/lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
  # The machine's own GL loaders first; the bundle's only where it has none.
  if ! ldconfig -p | grep -q 'libEGL\.so\.1 '; then
    export LD_LIBRARY_PATH="$LD_LIBRARY_PATH:$bundle/lib/glvnd"
    echo "gpu-check: no libEGL.so.1 on this machine: using the bundle's GLVND loaders"
  fi
  bench="$bundle/bin"
  gpu_tests="$bundle/bin/visq_gpu_tests"
  missing="$(ldd "$bundle"/bin/* 2> /dev/null | grep 'not found' | sort -u)"
  if [ -n "$missing" ]; then
    echo "gpu-check: libraries the bundle lacks here:"; echo "$missing"
    exit 1
  fi
else
  if [ ! -f "$build/CMakeCache.txt" ]; then
    step configure 30 cmake -S "$root" -B "$build" -DCMAKE_BUILD_TYPE=Release -DVISQ_DCHECKS=ON
  fi
  step build 60 cmake --build "$build" -j"$(nproc)"
  [ "$failed" -eq 0 ] || finish
  bench="$build/tests/bench"
  gpu_tests="$build/tests/gpu/visq_gpu_tests"
fi

# The device probe: the context test prints the renderer it got.
step renderer 10 "$gpu_tests" --gtest_filter='GpuContext.IsOpenGl45Core'
if grep -qi 'llvmpipe\|softpipe' "$out/renderer.log" 2> /dev/null; then
  summary+=("renderer                     FAILED: a software renderer answered, not the GPU")
  failed=1
  finish
fi
if [ -n "$bundle" ]; then
  # ctest's files name this build's paths, so the suites run one by one.
  while read -r suite; do
    step "$suite" 30 "$bundle/bin/$suite" --gtest_brief=1
  done < "$bundle/suites.txt"
else
  step gpu-test-suites 120 ctest --test-dir "$build" -L gpu -LE slow --output-on-failure -j4 --timeout 300
fi
step bench-rays 60 "$bench/visq_bench_rays" --quick --scenes "$scenes"
step bench-hidden-sample-map 60 "$bench/visq_bench_hidden_sample_map" --quick --scenes "$scenes"
step bench-hsm-copies 60 "$bench/visq_bench_hidden_sample_map" --copies 1,64 --scenes "$scenes"
step bench-slicemap 60 "$bench/visq_bench_slicemap" "$scenes" 3 2
step bench-volumetric 60 "$bench/visq_bench_volumetric" --quick --scene "$scenes/sponza_dabrovic/sponza.gltf"
step bench-obscurance 60 "$bench/visq_bench_obscurance" --quick --scenes "$scenes"
step bench-structures 30 "$bench/visq_bench_structures" --scenes "$scenes" --repeat 1 --only sponza
[ -n "$bundle" ] || step gpu-slow-suites 120 ctest --test-dir "$build" -L gpu -L slow --output-on-failure -j4 --timeout 300
finish
