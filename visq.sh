#!/usr/bin/env bash
# What a person does with a fresh checkout, as root on Debian 12:
#   ./visq.sh serve [visq-server flags...]   install, build, start the server
#   ./visq.sh test                           install, build, run every test
#   ./visq.sh container                      install, build the binaries, run test's stage 3 alone
#   ./visq.sh accuracy [bench flags...]      install, build, regenerate docs/accuracy.md and
#                                            its plots (the published accuracy/time trade)
#
# `test` runs three stages, each failing the command if it fails:
#   1. Release build, the package-list check (deploy/check-package-list.sh),
#      every test (ctest): unit, GPU on this machine's EGL device (llvmpipe
#      without a GPU), integration, deploy.
#   2. One clang build with AddressSanitizer, UndefinedBehaviorSanitizer and
#      libFuzzer coverage: the unit and integration tests again under the
#      sanitizers (VISQ_TEST_SANITIZERS=0 skips them), then the libFuzzer
#      targets, each for VISQ_FUZZ_SECONDS (default 30) from the corpus in
#      tests/fuzz/corpus (VISQ_FUZZ_SECONDS=0 skips them). Longer campaigns
#      are run by hand (docs/testing.md); CI's replays the corpus and looks
#      a little further.
#   3. The container: tests/deploy/container_test.sh packs stage 1's
#      binaries as the visq-server and visq-client .debs (cpack), builds the
#      image from deploy/Dockerfile around them with podman, runs it,
#      waits for SERVING and answers one query (a few seconds once the base
#      image and the runtime layer are cached; minutes the first time). A
#      machine that cannot run containers skips it, saying why in one line
#      and again in the last one; VISQ_TEST_CONTAINER=0 skips it,
#      VISQ_TEST_CONTAINER=required makes a skip fail.
set -euo pipefail
cd "$(dirname "$0")"

jobs=$(nproc 2>/dev/null || echo 2)
build_dir=${VISQ_BUILD_DIR:-build}
# Every command configures the one build folder alike, so `serve` after
# `test` (or the other way round) rebuilds nothing: Release with the debug
# checks kept (VISQ_DCHECKS: a few dozen value checks at invariants, none
# per ray or per fragment). VISQ_DCHECKS=OFF drops them, for every command.
configure() { cmake -S . -B "$build_dir" -DCMAKE_BUILD_TYPE=Release -DVISQ_DCHECKS="${VISQ_DCHECKS:-ON}"; }

stage() { printf '\n=== visq: %s ===\n' "$*"; }

# The container stage (tests/deploy/container_test.sh) on $build_dir's
# binaries. Sets `skipped` to the reason when this machine cannot run
# containers (the script's exit 77); exits 1 when the image fails.
container_stage() {
  skipped=
  if [[ "${VISQ_TEST_CONTAINER:-1}" == 0 ]]; then
    skipped="container stage skipped: VISQ_TEST_CONTAINER=0"
    echo "visq: $skipped"
    return
  fi
  local began=$SECONDS status=0
  # With pipefail the pipeline's status is the script's (tee's is 0).
  bash tests/deploy/container_test.sh "$build_dir" | tee "$build_dir/container-stage.log" || status=$?
  if [[ "$status" == 77 ]]; then
    skipped=$(sed -n 's/^visq: \(container stage skipped: .*\)/\1/p' "$build_dir/container-stage.log")
  elif [[ "$status" != 0 ]]; then
    echo "visq: the container stage failed after $((SECONDS - began)) s" >&2
    exit 1
  else
    echo "visq: the container stage took $((SECONDS - began)) s"
  fi
}

case "${1:-}" in
  serve)
    shift
    bash deploy/install-deps.sh
    configure
    cmake --build "$build_dir" -j"$jobs" --target visq-server visq
    repo=${VISQ_SCENE_REPO:-/var/lib/visq/scenes}
    echo "visq: starting visq-server on ${VISQ_ADDRESS:-127.0.0.1:50051}, scene repository $repo"
    exec "$build_dir/server/visq-server" --scene-repo "$repo" --seed-samples "$@"
    ;;
  test)
    shift
    start=$SECONDS
    bash deploy/install-deps.sh

    stage "1/3 Release build and every test"
    # Optimized as users run it, with the debug checks kept (VISQ_DCHECKS).
    configure
    began=$SECONDS
    cmake --build "$build_dir" -j"$jobs"
    echo "visq: the Release build took $((SECONDS - began)) s"
    # Every header, library and CMake file the build read is from a package
    # deploy/install-deps.sh lists or one they depend on (a clean machine has it).
    bash deploy/check-package-list.sh "$build_dir"
    ctest --test-dir "$build_dir" --output-on-failure -j"$jobs" --timeout 900 "$@"

    sanitized_tests=${VISQ_TEST_SANITIZERS:-1}
    fuzz_seconds=${VISQ_FUZZ_SECONDS:-30}
    if [[ "$sanitized_tests" != 0 || "$fuzz_seconds" != 0 ]]; then
      stage "2/3 clang build with ASan + UBSan: the tests under the sanitizers, then fuzzing ${fuzz_seconds} s per target"
      asan_dir="${build_dir}-asan"
      began=$SECONDS
      # -O1 without debug info: the sanitizers need no more, and the build is
      # the longest part of this command on a 2-core machine.
      CC=clang CXX=clang++ cmake -S . -B "$asan_dir" -DCMAKE_BUILD_TYPE=None -DCMAKE_CXX_FLAGS=-O1 \
        -DVISQ_SANITIZE=ON -DVISQ_FUZZ=ON -DVISQ_FUZZ_SECONDS="$fuzz_seconds"
      cmake --build "$asan_dir" -j"$jobs" --target visq-server visq visq_scene_tests visq_gpu_tests \
        visq_integration_tests visq_operability_tests visq_service_tests visq_raycast_tests visq_rays_tests visq_exact_tests \
        visq_core_tests \
        gltf_loader_fuzz gltf_structure_fuzz request_validation_fuzz algorithm_request_fuzz
      echo "visq: the sanitized build took $((SECONDS - began)) s"
      if [[ "$sanitized_tests" != 0 ]]; then
        # LeakSanitizer cannot follow Mesa's and the NVIDIA driver's own
        # allocations; ASan's use-after-free and overflow checks still apply.
        # Left out under the sanitizers: the tests that time the server
        # (tests/integration/timed_tests.txt says why).
        unsanitized=$(grep -E '^[A-Za-z]' tests/integration/timed_tests.txt | paste -sd: -)
        for test in scene/visq_scene_tests gpu/visq_gpu_tests raycast/visq_raycast_tests rays/visq_rays_tests exact/visq_exact_tests \
                    core/visq_core_tests service/visq_service_tests integration/visq_integration_tests \
                    integration/visq_operability_tests; do
          echo "--- $test (ASan + UBSan)"
          ASAN_OPTIONS=detect_leaks=0:abort_on_error=1 UBSAN_OPTIONS=print_stacktrace=1:halt_on_error=1 \
            "$asan_dir/tests/$test" --gtest_brief=1 --gtest_filter="-$unsanitized"
        done
      fi
      if [[ "$fuzz_seconds" != 0 ]]; then
        ASAN_OPTIONS=detect_leaks=0 ctest --test-dir "$asan_dir" --output-on-failure -R fuzz
      fi
    fi
    stage "3/3 the container: the image built from deploy/Dockerfile, run, SERVING and one query"
    container_stage
    echo "visq: every stage passed in $((SECONDS - start)) s${skipped:+ (${skipped})}"
    ;;
  container)
    # test's stage 3 alone: what its four .debs hold (the two binaries, the
    # client libraries, the Python stubs), then the image built and run.
    shift
    bash deploy/install-deps.sh
    configure
    cmake --build "$build_dir" -j"$jobs" --target visq-server visq visq_client visq_proto visq_python_stubs
    stage "the container: the image built from deploy/Dockerfile, run, SERVING and one query"
    container_stage
    echo "visq: ${skipped:-container stage passed}"
    ;;
  accuracy)
    # The published trade (issue 8): sweeps every query kind's accuracy
    # parameters on the shared real scenes and rewrites docs/accuracy.md and
    # docs/accuracy/*.png (about 20 minutes on 2 cores with llvmpipe).
    shift
    bash deploy/install-deps.sh
    configure
    cmake --build "$build_dir" -j"$jobs" --target visq_bench_accuracy_trade
    scenes=${VISQ_SHARED_SCENES:-../shared/scenes}
    exec "$build_dir/tests/bench/visq_bench_accuracy_trade" --scenes "$scenes" --out docs \
      --command "./visq.sh accuracy $*" "$@"
    ;;
  *)
    echo "usage: $0 serve [visq-server flags...] | test [ctest flags...] | container | accuracy [bench flags...]" >&2
    exit 2
    ;;
esac
