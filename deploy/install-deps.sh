#!/usr/bin/env bash
# Installs every Debian 12 package visq needs to build, test and run.
# This is the only place that lists apt packages; the README, .ci/run and the
# Dockerfile all call it. Idempotent: packages already present are skipped.
set -euo pipefail

build_packages=(
  build-essential cmake pkg-config ca-certificates
  protobuf-compiler protobuf-compiler-grpc libprotobuf-dev libgrpc++-dev libgrpc-dev
  libegl-dev libgl-dev libepoxy-dev
  libglm-dev libtinygltf-dev nlohmann-json3-dev libstb-dev
  libspdlog-dev libfmt-dev libcli11-dev libabsl-dev
  libembree-dev libgmp-dev libxxhash-dev
  openssl nginx-light
  libgtest-dev libgmock-dev libbenchmark-dev
)
# Mesa's EGL/GL drivers (llvmpipe) for machines without an NVIDIA GPU.
runtime_packages=(libegl1 libegl-mesa0 libgl1-mesa-dri libgles2 libopengl0)

wanted=("${build_packages[@]}" "${runtime_packages[@]}")
if [[ "${1:-}" == "--runtime-only" ]]; then
  wanted=("${runtime_packages[@]}"
    libgrpc++1.51 libprotobuf32 libspdlog1.10 libfmt9 libembree3-3 libepoxy0 libgmp10 libstdc++6)
fi

missing=()
for pkg in "${wanted[@]}"; do
  dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || missing+=("$pkg")
done
if (( ${#missing[@]} == 0 )); then
  echo "install-deps: all ${#wanted[@]} packages present"
  exit 0
fi
echo "install-deps: installing ${missing[*]}"
export DEBIAN_FRONTEND=noninteractive
apt-get update -qq
apt-get install -y -qq --no-install-recommends "${missing[@]}"
