#!/usr/bin/env bash
# Installs every Debian 12 package visq needs to build, test and run.
# This is the only place that lists apt packages; the README, .ci/run and the
# Dockerfile all call it. Idempotent: packages already present are skipped.
#   install-deps.sh [--runtime-only | --without-container-tools] [--print]
# --runtime-only: what a machine that only runs visq-server and the visq CLI
# needs, and nothing to build with (runtime_packages below; the Dockerfile's
# slim stage). The visq-server and visq-client .debs (cmake/Package.cmake)
# depend on exactly these: the container stage installs them with dpkg on a
# root that has this list alone, and fails where the list names a package
# neither .deb needs.
# --print writes the wanted packages, one a line, and installs nothing
# (deploy/check-package-list.sh reads the list this way).
# --without-container-tools: all but the container stage's tools and the
# test-only tools (the Dockerfile's build stage: an image has no use for
# podman, and it builds no tests).
set -euo pipefail

runtime_only=0 print_only=0 container_tools=1
for arg in "$@"; do
  case "$arg" in
    --runtime-only) runtime_only=1 ;;
    --without-container-tools) container_tools=0 ;;
    --print) print_only=1 ;;
    *) echo "usage: $0 [--runtime-only | --without-container-tools] [--print]" >&2; exit 2 ;;
  esac
done

build_packages=(
  build-essential cmake pkg-config ca-certificates
  protobuf-compiler protobuf-compiler-grpc libprotobuf-dev libgrpc++-dev libgrpc-dev
  libegl-dev libgl-dev libopengl-dev libepoxy-dev
  libglm-dev libeigen3-dev libtinygltf-dev nlohmann-json3-dev libstb-dev
  libspdlog-dev libfmt-dev libcli11-dev libabsl-dev
  libembree-dev libgmp-dev libxxhash-dev
  openssl nginx-light libyaml-cpp-dev libcpp-httplib-dev
  clang libclang-rt-14-dev
  libgtest-dev libgmock-dev libbenchmark-dev
  gnuplot-nox
  # The Python client (client/python): its runtime, the venv its test installs
  # it into offline, and pip and wheel for its wheel (visq_python_wheel).
  python3-grpcio python3-protobuf python3-numpy python3-venv python3-setuptools python3-pip python3-wheel
  # The CLI's float images (--exr).
  libopenexr-dev
  # Compressed glTF (EXT_meshopt_compression, KHR_draco_mesh_compression).
  libmeshoptimizer-dev libdraco-dev
  # The scene repository: its catalog in SQLite (the default) or PostgreSQL
  # (libpq, replicas on several machines), its blobs named by SHA-256
  # (libcrypto); the replica race test starts a PostgreSQL cluster of its own.
  libsqlite3-dev libpq-dev libssl-dev postgresql
  # The .debs (cpack -G DEB): CPack's dpkg-shlibdeps step runs file(1) on
  # each binary; a minimal Debian root has no file.
  file
)
# What visq-server and the visq CLI run with: the libraries the two binaries
# load (ldd: what dpkg-shlibdeps puts in the .debs' Depends and the libraries
# those load; libc6, libgcc-s1 and libstdc++6 are in every Debian root),
# Mesa's EGL/GL drivers (llvmpipe, for machines without an NVIDIA GPU; loaded
# through libglvnd, not linked) and the CA certificates (visq-server
# recommends them).
runtime_packages=(
  libegl1 libegl-mesa0 libgl1-mesa-dri libgles2 libopengl0 ca-certificates
  libabsl20220623 libc-ares2 libepoxy0 libfmt9 libgrpc++1.51 libgrpc29 libprotobuf32 libre2-9
  libspdlog1.10 libssl3 libstb0 libtinygltf2d libxxhash0 libembree3-3 libtbb12 libgmp10
  libopenexr-3-1-30 libimath-3-1-29 libmeshoptimizer2d libsqlite3-0 libpq5
)

# ./visq.sh test's container stage (tests/deploy/container_test.sh): podman
# builds and runs the image with runc (as root: no user namespaces, so no
# uidmap), on a debian:bookworm base that debootstrap makes once.
container_packages=(podman runc debootstrap)

# The baked glTF's tests (tests/gltf_export): the Khronos glTF validator runs
# on node (npm installs it into the build folder from a committed lock), and
# Blender imports the file in background mode (blender -b; about 300 MB with
# its libraries). The add-on's modal operators run in Blender with a window
# on a virtual X display (tests/blender: xvfb-run, which needs xauth). Test
# tools only: an image's build stage, which builds no tests, leaves them out
# with the container tools.
test_tool_packages=(nodejs npm blender xvfb xauth)

wanted=("${build_packages[@]}" "${runtime_packages[@]}")
if (( container_tools )); then wanted+=("${container_packages[@]}" "${test_tool_packages[@]}"); fi
if (( runtime_only )); then wanted=("${runtime_packages[@]}"); fi

if (( print_only )); then
  printf '%s\n' "${wanted[@]}"
  exit 0
fi

# A package counts as present when it is installed, or when an installed
# package provides it (NodeSource's nodejs provides npm and conflicts with
# Debian's: asking apt for npm there would fail).
provided=" $(dpkg-query -W -f='${db:Status-Abbrev} ${Provides}\n' 2>/dev/null | awk '/^ii/ { $1 = ""; print }' |
  tr ',' '\n' | sed 's/(.*)//; s/^ *//; s/ *$//' | tr '\n' ' ') "
missing=()
for pkg in "${wanted[@]}"; do
  dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" ||
    [[ "$provided" == *" $pkg "* ]] || missing+=("$pkg")
done
if (( ${#missing[@]} == 0 )); then
  echo "install-deps: all ${#wanted[@]} packages present"
  exit 0
fi
echo "install-deps: installing ${missing[*]}"
export DEBIAN_FRONTEND=noninteractive
# Packages install, services do not start: the tests run nginx themselves on
# loopback, and a build machine needs no web server listening.
policy=/usr/sbin/policy-rc.d
if [[ ! -e "$policy" ]]; then
  printf '#!/bin/sh\nexit 101\n' > "$policy"
  chmod +x "$policy"
  trap 'rm -f "$policy"' EXIT
fi
apt-get update -qq
apt-get install -y -qq --no-install-recommends "${missing[@]}"
