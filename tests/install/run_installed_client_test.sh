#!/usr/bin/env bash
# Installs the build tree into a scratch prefix, builds tests/install/consumer
# against that prefix alone, twice (CMake's find_package(visq CONFIG) and
# pkg-config visq-client), starts the installed visq-server on a free
# loopback port with the sample scenes, and checks that both builds of the
# consumer list the sample scene.
#   run_installed_client_test.sh BUILD_DIR CONSUMER_SOURCE CMAKE CXX PKG_CONFIG LIBDIR
# LIBDIR: CMAKE_INSTALL_LIBDIR (lib, or lib/x86_64-linux-gnu for a /usr prefix).
set -euo pipefail
build=$(cd "$1" && pwd) consumer=$2 cmake=$3 cxx=$4 pkg_config=$5 libdir=$6
scratch=$(mktemp -d /tmp/visq-install-XXXXXX)
source "$(dirname "${BASH_SOURCE[0]}")/script_support.sh"
prefix=$scratch/prefix

step "cmake --install $build --prefix $prefix"
"$cmake" --install "$build" --prefix "$prefix" > "$scratch/install.log" || { cat "$scratch/install.log"; fail "install"; }
for file in bin/visq-server bin/visq include/visq/visq_client.h include/visq/status.h \
            include/visq/obscurance_partial.h include/visq/v1/visq.grpc.pb.h \
            include/visq/grpc/health/v1/health.grpc.pb.h "$libdir/libvisq_client.a" "$libdir/libvisq_proto.a" \
            "$libdir/cmake/visq/visqConfig.cmake" "$libdir/cmake/visq/visqConfigVersion.cmake" \
            "$libdir/cmake/visq/visqTargets.cmake" "$libdir/pkgconfig/visq-client.pc" share/visq/proto/visq/v1/visq.proto \
            share/visq/proto/grpc/health/v1/health.proto; do
  [[ -e "$prefix/$file" ]] || fail "the install has no $file"
done

# A copy of the consumer, so that nothing it builds can see the checkout.
cp -r "$consumer" "$scratch/consumer"

# pkg-config's build overlaps CMake's (two cores).
step "c++ main.cpp \$(pkg-config --cflags --libs visq-client)"
(
  flags=$(PKG_CONFIG_PATH="$prefix/$libdir/pkgconfig" "$pkg_config" --cflags --libs visq-client)
  "$cxx" -std=c++17 -O0 "$scratch/consumer/main.cpp" $flags -o "$scratch/consumer_pkg_config"
) > "$scratch/pkg-config.log" 2>&1 &
pkg_config_build=$!

step "cmake -DCMAKE_PREFIX_PATH=$prefix: find_package(visq CONFIG REQUIRED), visq::client"
"$cmake" -S "$scratch/consumer" -B "$scratch/consumer-build" -DCMAKE_PREFIX_PATH="$prefix" \
  -DCMAKE_CXX_COMPILER="$cxx" -DCMAKE_FIND_USE_PACKAGE_REGISTRY=OFF \
  > "$scratch/configure.log" 2>&1 || { cat "$scratch/configure.log"; fail "configuring the consumer"; }
"$cmake" --build "$scratch/consumer-build" > "$scratch/build.log" 2>&1 ||
  { cat "$scratch/build.log"; fail "building the consumer with CMake"; }
wait "$pkg_config_build" || { cat "$scratch/pkg-config.log"; fail "building the consumer with pkg-config"; }
# The consumer's compile and link lines name the prefix, never the build tree.
if grep -rl -F "$build" "$scratch/consumer-build/CMakeFiles/visq_consumer.dir"/{flags.make,link.txt}; then
  fail "the consumer's build reads the build tree"
fi

step "the installed visq-server on a free loopback port, --seed-samples"
mkdir "$scratch/repo"
"$prefix/bin/visq-server" --address 127.0.0.1:0 --port-file "$scratch/port" --scene-repo "$scratch/repo" \
  --seed-samples --drain-seconds 1 > "$scratch/server.log" 2>&1 &
server_pid=$!
wait_for_port

for consumer_binary in consumer-build/visq_consumer consumer_pkg_config; do
  step "$consumer_binary 127.0.0.1:$port"
  "$scratch/$consumer_binary" "127.0.0.1:$port" > "$scratch/out.txt" 2>&1 ||
    { cat "$scratch/out.txt"; fail "$consumer_binary"; }
  cat "$scratch/out.txt"
  grep -qx "health SERVING" "$scratch/out.txt" || fail "$consumer_binary printed no 'health SERVING'"
  grep -q "^scene cornell_box_visq [1-9]" "$scratch/out.txt" || fail "$consumer_binary did not list cornell_box_visq"
done
step "the installed visq CLI"
"$prefix/bin/visq" --server "127.0.0.1:$port" health | grep -qx SERVING || fail "bin/visq health"
step "passed"
