#!/usr/bin/env bash
# The Debian packages and the wheel as a studio installs them
# (cmake/Package.cmake):
#   run_package_test.sh BUILD_DIR SOURCE_DIR CMAKE CXX PKG_CONFIG
# 1. cpack makes visq-server, visq-client, libvisq-client-dev and
#    python3-visq from BUILD_DIR (which must be built: the binaries, the
#    client libraries, the Python stubs); each holds what it should, and the
#    server's and the CLI's Depends name only packages that
#    deploy/install-deps.sh --runtime-only lists (or that every Debian root has).
# 2. The four are unpacked (dpkg -x) into one scratch root, not installed:
#    this machine is a build machine, and its own /usr stays as it is. The
#    server runs from there with the environment of its systemd unit (paths
#    moved into the scratch folder): it makes its token at first start, mode
#    0600; the packaged CLI, the packaged Python package (no protoc on PATH,
#    nothing of the checkout on sys.path) and a find_package(visq) consumer
#    built against the unpacked libvisq-client-dev alone answer through it.
# 3. The wheel: built offline from the checkout's client/python with pip,
#    the stubs inside; pip install of the checkout (the README's command)
#    and of the wheel write nothing into client/python; the installed wheel
#    answers Health.
# The clean-root installs (dpkg -i of all four on debian:bookworm-slim
# roots, visq-server's and visq-client's Depends against the run-time list)
# are ./visq.sh test's container stage (tests/deploy/container_test.sh); this
# test covers machines where that stage cannot run.
set -euo pipefail
export LC_ALL=C
build=$(cd "$1" && pwd) source_dir=$(cd "$2" && pwd) cmake=$3 cxx=$4 pkg_config=$5
python=/usr/bin/python3
scratch=$(mktemp -d /tmp/visq-packages-XXXXXX)
source "$(dirname "${BASH_SOURCE[0]}")/script_support.sh"
for tool in dpkg-deb dpkg-shlibdeps; do
  command -v "$tool" > /dev/null || fail "no $tool (dpkg-dev; deploy/install-deps.sh installs it)"
done

# --- 1. The packages ----------------------------------------------------------
step "cpack -G DEB in $build"
(cd "$build" && cpack -G DEB -B "$scratch/packages") > "$scratch/cpack.log" 2>&1 ||
  { tail -n 20 "$scratch/cpack.log"; fail "cpack (is $build built? cmake --build $build)"; }
declare -A deb=()
for package in visq-server visq-client libvisq-client-dev python3-visq; do
  deb[$package]=$(ls "$scratch/packages/${package}"_*.deb 2> /dev/null) || fail "cpack made no $package .deb"
  printf '  %-36s %6d KiB\n' "$(basename "${deb[$package]}")" $(( $(stat -c %s "${deb[$package]}") / 1024 ))
  dpkg-deb -c "${deb[$package]}" | awk '{ print $6 }' | sed 's#^\./#/#' > "$scratch/$package.files"
done
has() {  # has PACKAGE FILE...
  local package=$1 file
  shift
  for file in "$@"; do grep -qx -- "$file" "$scratch/$package.files" || fail "$package has no $file"; done
}
has visq-server /usr/bin/visq-server /usr/lib/systemd/system/visq-server.service /usr/share/visq-server/default
has visq-client /usr/bin/visq
has libvisq-client-dev /usr/include/visq/visq_client.h /usr/include/visq/status.h /usr/include/visq/v1/visq.grpc.pb.h \
  /usr/include/visq/grpc/health/v1/health.grpc.pb.h /usr/lib/libvisq_client.a /usr/lib/libvisq_proto.a \
  /usr/lib/cmake/visq/visqConfig.cmake /usr/lib/cmake/visq/visqTargets.cmake /usr/lib/pkgconfig/visq-client.pc \
  /usr/share/visq/proto/visq/v1/visq.proto
has python3-visq /usr/lib/python3/dist-packages/visq/__init__.py /usr/lib/python3/dist-packages/visq/client.py \
  /usr/lib/python3/dist-packages/visq/v1/__init__.py /usr/lib/python3/dist-packages/visq/v1/visq_pb2.py \
  /usr/lib/python3/dist-packages/visq/v1/visq_pb2_grpc.py
if grep -q -e __pycache__ -e '\.pyc$' "$scratch/python3-visq.files"; then fail "python3-visq ships compiled files"; fi
[[ $(dpkg-deb -f "${deb[python3-visq]}" Architecture) == all ]] || fail "python3-visq is not Architecture: all"
dpkg-deb -I "${deb[visq-server]}" postinst > /dev/null 2>&1 || fail "visq-server has no postinst (the user, the service)"

# Depends as names, one a line ("a (>= 1) | b" gives a and b).
depends() { dpkg-deb -f "$1" Depends | tr ',|' '\n\n' | sed 's/(.*)//; s/^ *//; s/ *$//' | sed '/^$/d' | sort -u; }
depends "${deb[visq-server]}" > "$scratch/server.depends"
grep -qx libgrpc++1.51 "$scratch/server.depends" || fail "visq-server's Depends lack the libraries (dpkg-shlibdeps): $(tr '\n' ' ' < "$scratch/server.depends")"
grep -qx libegl-mesa0 "$scratch/server.depends" || fail "visq-server does not depend on Mesa's EGL driver"
# The list's names, the virtual names they provide (libspdlog1.10 provides
# the libspdlog1.10-fmt9 its shlibs file gives), and what every root has.
bash "$source_dir/deploy/install-deps.sh" --runtime-only --print > "$scratch/runtime.list"
xargs dpkg-query -W -f='${Provides}\n' < "$scratch/runtime.list" 2> /dev/null | tr ',' '\n' |
  sed 's/(.*)//; s/^ *//; s/ *$//' | sed '/^$/d' >> "$scratch/runtime.list" || true
printf '%s\n' libc6 libgcc-s1 libstdc++6 >> "$scratch/runtime.list"
for package in visq-server visq-client; do
  extra=$(depends "${deb[$package]}" | grep -vxF -f "$scratch/runtime.list" | tr '\n' ' ' || true)
  [[ -z "$extra" ]] || fail "$package depends on $extra, which deploy/install-deps.sh --runtime-only does not list"
done
for package in libvisq-client-dev python3-visq; do
  for name in $(depends "${deb[$package]}"); do
    dpkg-query -W -f='${Status}' "$name" 2> /dev/null | grep -q "install ok installed" ||
      fail "$package depends on $name, which this build machine does not have (deploy/install-deps.sh)"
  done
done
step "the four packages hold what they should; visq-server and visq-client depend on the run-time list alone"

# --- 2. Unpacked into one root, used ---------------------------------------------
root=$scratch/root
for package in "${!deb[@]}"; do dpkg-deb -x "${deb[$package]}" "$root"; done
unit=$root/usr/lib/systemd/system/visq-server.service
grep -qx 'ExecStart=/usr/bin/visq-server' "$unit" || fail "the unit does not start /usr/bin/visq-server"
grep -qx 'Environment=VISQ_AUTH_TOKEN_CREATE=1' "$unit" || fail "the unit does not make a token at first start"
grep -qx 'User=visq' "$unit" || fail "the unit does not run as visq"
if command -v systemd-analyze > /dev/null; then
  # The unit's syntax (its ExecStart is not installed here: that one warning is expected).
  systemd-analyze verify "$unit" > "$scratch/verify.log" 2>&1 || true
  if grep -v -e 'visq-server is not executable' -e 'No such file or directory' -e 'Failed to prepare' "$scratch/verify.log" |
      grep -i -e 'unknown' -e 'invalid' -e 'failed to parse' > "$scratch/verify-errors.log"; then
    cat "$scratch/verify-errors.log"
    fail "systemd-analyze verify finds errors in the unit"
  fi
fi

step "the unpacked visq-server with its unit's environment (paths under $scratch/state)"
mkdir -p "$scratch/state/scenes"
mapfile -t unit_env < <(sed -n 's/^Environment=//p' "$unit")
env "${unit_env[@]}" VISQ_ADDRESS=127.0.0.1:0 VISQ_SCENE_REPO="$scratch/state/scenes" \
  VISQ_AUTH_TOKEN_FILE="$scratch/state/token" XDG_CACHE_HOME="$scratch/state/cache" \
  "$root/usr/bin/visq-server" --port-file "$scratch/port" --drain-seconds 1 > "$scratch/server.log" 2>&1 &
server_pid=$!
wait_for_port
server=127.0.0.1:$port
[[ -s "$scratch/state/token" ]] || fail "no token made at first start in VISQ_AUTH_TOKEN_FILE"
[[ $(stat -c %a "$scratch/state/token") == 600 ]] || fail "the token's mode is $(stat -c %a "$scratch/state/token"), not 600"

step "the packaged CLI"
cli=$root/usr/bin/visq
"$cli" health --server "$server" --timeout 60 > "$scratch/out.txt" 2>&1 || { cat "$scratch/out.txt"; fail "visq health"; }
grep -qx SERVING "$scratch/out.txt" || fail "visq health: $(cat "$scratch/out.txt")"
if "$cli" list --server "$server" > "$scratch/out.txt" 2>&1; then fail "visq list without the token was answered"; fi
"$cli" list --server "$server" --token-file "$scratch/state/token" > "$scratch/out.txt" 2>&1 ||
  { cat "$scratch/out.txt"; fail "visq list --token-file"; }
grep -q "^cornell_box_visq " "$scratch/out.txt" || fail "visq list: $(cat "$scratch/out.txt")"

# Python: only the given folders on sys.path, no protoc on PATH, from a
# folder that is not the checkout.
python_health() {  # python_health PYTHON [PYTHONPATH]
  (cd "$scratch" && env -i HOME="$scratch" PATH=/nonexistent ${2:+PYTHONPATH="$2"} "$1" -c '
import sys, visq
server, token, expected = sys.argv[1], sys.argv[2], sys.argv[3]
assert visq.__file__.startswith(expected), visq.__file__
import visq.v1.visq_pb2_grpc
with visq.Client(server, token_file=token) as c:
    print("health", c.health())
    print("scenes", len(c.list_scenes()))
' "$server" "$scratch/state/token" "$3") > "$scratch/out.txt" 2>&1 || { cat "$scratch/out.txt"; fail "$4"; }
  grep -qx "health SERVING" "$scratch/out.txt" || fail "$4: $(cat "$scratch/out.txt")"
}
step "the packaged Python package (python3-visq)"
python_health "$python" "$root/usr/lib/python3/dist-packages" "$root/usr/lib/python3/dist-packages/visq/" \
  "import visq from python3-visq"

step "a find_package(visq) consumer built against the unpacked libvisq-client-dev alone"
cp -r "$source_dir/tests/install/consumer" "$scratch/consumer"
"$cmake" -S "$scratch/consumer" -B "$scratch/consumer-build" -DCMAKE_PREFIX_PATH="$root/usr" \
  -DCMAKE_CXX_COMPILER="$cxx" -DCMAKE_FIND_USE_PACKAGE_REGISTRY=OFF > "$scratch/configure.log" 2>&1 ||
  { cat "$scratch/configure.log"; fail "configuring the consumer"; }
grep -q "^visq_DIR:PATH=$root/usr/lib/cmake/visq$" "$scratch/consumer-build/CMakeCache.txt" ||
  fail "find_package(visq) did not find the unpacked package: $(grep '^visq_DIR' "$scratch/consumer-build/CMakeCache.txt")"
"$cmake" --build "$scratch/consumer-build" > "$scratch/build.log" 2>&1 || { cat "$scratch/build.log"; fail "building the consumer"; }
VISQ_TOKEN=$(head -n 1 "$scratch/state/token") "$scratch/consumer-build/visq_consumer" "$server" > "$scratch/out.txt" 2>&1 ||
  { cat "$scratch/out.txt"; fail "visq_consumer"; }
grep -qx "health SERVING" "$scratch/out.txt" && grep -q "^scene cornell_box_visq [1-9]" "$scratch/out.txt" ||
  fail "visq_consumer: $(cat "$scratch/out.txt")"
step "the same consumer built with pkg-config visq-client against the unpacked package"
flags=$(PKG_CONFIG_PATH="$root/usr/lib/pkgconfig" "$pkg_config" --cflags --libs visq-client) || fail "pkg-config visq-client"
# shellcheck disable=SC2086 # the flags are words
"$cxx" -std=c++17 -O0 "$scratch/consumer/main.cpp" $flags -o "$scratch/consumer_pkg_config" > "$scratch/build.log" 2>&1 ||
  { cat "$scratch/build.log"; fail "building the consumer with pkg-config"; }
VISQ_TOKEN=$(head -n 1 "$scratch/state/token") "$scratch/consumer_pkg_config" "$server" > "$scratch/out.txt" 2>&1 ||
  { cat "$scratch/out.txt"; fail "consumer_pkg_config"; }
grep -qx "health SERVING" "$scratch/out.txt" || fail "consumer_pkg_config: $(cat "$scratch/out.txt")"

# --- 3. The wheel ---------------------------------------------------------------
# What client/python holds that git ignores (a build there would add to it).
checkout_state() { find "$source_dir/client/python" -maxdepth 1 \( -name build -o -name '*.egg-info' -o -name dist \) | sort; }
before=$(checkout_state)
step "pip install ./client/python (the README's command) and pip wheel, offline"
"$python" -m venv --system-site-packages "$scratch/venv"
(cd "$source_dir" && VISQ_PROTO_DIR="$source_dir/proto" "$scratch/venv/bin/pip" install --quiet --no-build-isolation \
  --no-index --disable-pip-version-check ./client/python) > "$scratch/pip.log" 2>&1 ||
  { cat "$scratch/pip.log"; fail "pip install ./client/python"; }
VISQ_PROTO_DIR="$source_dir/proto" VISQ_PYTHON_BUILD_DIR="$scratch/wheel-build" "$python" -m pip wheel --quiet \
  --no-build-isolation --no-index --no-deps --disable-pip-version-check -w "$scratch/wheel" "$source_dir/client/python" \
  > "$scratch/pip.log" 2>&1 || { cat "$scratch/pip.log"; fail "pip wheel client/python"; }
[[ "$(checkout_state)" == "$before" ]] || fail "building the Python package wrote into the checkout: $(checkout_state)"
wheel=$(ls "$scratch/wheel"/visq-*-py3-none-any.whl 2> /dev/null) || fail "pip wheel made no visq wheel"
"$python" -m zipfile -l "$wheel" > "$scratch/wheel.files"
for file in visq/client.py visq/v1/visq_pb2.py visq/v1/visq_pb2_grpc.py; do
  grep -q "^$file " "$scratch/wheel.files" || fail "the wheel has no $file"
done
printf '  %-36s %6d KiB\n' "$(basename "$wheel")" $(( $(stat -c %s "$wheel") / 1024 ))
"$scratch/venv/bin/pip" install --quiet --no-index --no-deps --force-reinstall --disable-pip-version-check "$wheel" \
  > "$scratch/pip.log" 2>&1 || { cat "$scratch/pip.log"; fail "pip install the wheel"; }
python_health "$scratch/venv/bin/python" "" "$scratch/venv/lib/" "import visq from the wheel"
step "passed"
