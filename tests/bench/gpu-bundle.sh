#!/usr/bin/env bash
# Packs a built tree's GPU test suites and GPU benchmarks, with the shared
# libraries they load, into one folder that runs on an NVIDIA machine which
# has the driver but not Debian's development packages (a rented GPU box, a
# CUDA container image). gpu-check.sh --bundle DIR runs it there.
#
#   tests/bench/gpu-bundle.sh [--build DIR] [--scenes DIR] OUT_DIR | OUT.tar.gz
#
# Given a name ending in .tar.gz it writes one archive (Embree's many-ISA
# library makes the folder about 80 MB, the archive about 35).
#
# --build DIR   the built tree (default build)
# --scenes DIR  the shared real scenes to copy in (default ../shared/scenes);
#               without them the suites and benchmarks that need them skip
#
# What is left out: the C and C++ runtimes (glibc, libstdc++, libgcc_s),
# which the target's newer ones serve, and which the NVIDIA driver's own
# libraries need at their version. GLVND's loaders (libEGL, libOpenGL) go in
# lib/glvnd, which gpu-check.sh uses only when the machine has none.
set -eu -o pipefail

root="$(cd "$(dirname "$0")/../.." && pwd)"
build="$root/build"
scenes="$root/../shared/scenes"
while [ $# -gt 1 ]; do
  case "$1" in
    --build) build="$(realpath -m "$2")"; shift 2 ;;
    --scenes) scenes="$(realpath -m "$2")"; shift 2 ;;
    *) break ;;
  esac
done
[ $# -eq 1 ] || { echo "usage: $0 [--build DIR] [--scenes DIR] OUT_DIR" >&2; exit 2; }
out="$(realpath -m "$1")"
archive=""
if [[ "$out" == *.tar.gz ]]; then
  archive="$out"
  staging="$(mktemp -d)"
  trap 'rm -rf "$staging"' EXIT
  out="$staging/gpu-bundle"
fi

# The suites labelled gpu, as ctest knows them, and the GPU benchmarks that
# gpu-check.sh runs.
mapfile -t suites < <(ctest --test-dir "$build" -L gpu -N -V 2> /dev/null |
  sed -n 's/^[0-9]*: Test command: \([^ ]*visq_[a-z_]*_tests\).*/\1/p' | sort -u)
[ "${#suites[@]}" -gt 0 ] || { echo "gpu-bundle: no gpu suites found in $build (is it built?)" >&2; exit 1; }
benches=(visq_bench_rays visq_bench_hidden_sample_map visq_bench_slicemap visq_bench_volumetric visq_bench_obscurance
         visq_bench_structures)

rm -rf "$out"
mkdir -p "$out/bin" "$out/lib/glvnd"
for suite in "${suites[@]}"; do cp "$suite" "$out/bin/"; done
for bench in "${benches[@]}"; do cp "$build/tests/bench/$bench" "$out/bin/"; done
strip --strip-unneeded "$out"/bin/*

runtime='^(linux-vdso|ld-linux|libc|libm|libdl|libpthread|librt|libstdc\+\+|libgcc_s)\.'
for binary in "$out"/bin/*; do
  ldd "$binary" | awk '$3 ~ /^\// { print $1, $3 }'
done | sort -u | while read -r name path; do
  if [[ "$name" =~ $runtime ]]; then continue; fi
  cp -L "$path" "$out/lib/$name"
done
# libepoxy opens the GL loaders at run time, so ldd does not list them.
for name in libEGL.so.1 libOpenGL.so.0 libGLdispatch.so.0 libGL.so.1 libGLX.so.0; do
  path="$(ldconfig -p | awk -v n="$name" '$1 == n && /x86-64/ { print $NF; exit }')"
  [ -n "$path" ] && cp -L "$path" "$out/lib/glvnd/$name"
done

if [ -d "$scenes" ]; then
  cp -r "$scenes" "$out/scenes"
else
  echo "gpu-bundle: no scenes at $scenes; the bundle's scene tests and benchmarks will skip" >&2
fi
printf '%s\n' "${suites[@]##*/}" > "$out/suites.txt"
git -C "$root" rev-parse HEAD > "$out/commit.txt" 2> /dev/null || true
summary="${#suites[@]} suites, ${#benches[@]} benchmarks, $(du -sh "$out" | cut -f1)"
if [ -n "$archive" ]; then
  tar -C "$(dirname "$out")" -czf "$archive" gpu-bundle
  echo "gpu-bundle: $archive ($(du -sh "$archive" | cut -f1)): $summary"
else
  echo "gpu-bundle: $out: $summary"
fi
