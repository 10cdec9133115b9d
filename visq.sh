#!/usr/bin/env bash
# The two things a person does with a fresh checkout, as root on Debian 12:
#   ./visq.sh serve [visq-server flags...]   install, build, start the server
#   ./visq.sh test                           install, build, run every test
set -euo pipefail
cd "$(dirname "$0")"

jobs=$(nproc 2>/dev/null || echo 2)
build_dir=${VISQ_BUILD_DIR:-build}

configure() {
  bash deploy/install-deps.sh
  cmake -S . -B "$build_dir" -DCMAKE_BUILD_TYPE=Release "$@"
}

case "${1:-}" in
  serve)
    shift
    configure
    cmake --build "$build_dir" -j"$jobs" --target visq-server visq
    repo=${VISQ_SCENE_REPO:-/var/lib/visq/scenes}
    echo "visq: starting visq-server on ${VISQ_ADDRESS:-127.0.0.1:50051}, scene repository $repo"
    exec "$build_dir/server/visq-server" --scene-repo "$repo" --seed-samples "$@"
    ;;
  test)
    shift
    configure
    cmake --build "$build_dir" -j"$jobs"
    ctest --test-dir "$build_dir" --output-on-failure -j"$jobs" --timeout 900 "$@"
    ;;
  *)
    echo "usage: $0 serve [visq-server flags...] | test [ctest flags...]" >&2
    exit 2
    ;;
esac
