#!/usr/bin/env bash
# container_test.sh BUILD_DIR
# Builds the visq image from deploy/Dockerfile with podman and runs it: health
# SERVING, the token made in the volume as the Dockerfile documents, one real
# query answered, a clean stop. ./visq.sh test runs it as its own stage.
#
# The image is the Dockerfile's runtime-prebuilt target: BUILD_DIR's
# visq-server and visq (built on this Debian 12 host, as the image is),
# packed here as the visq-server and visq-client .debs (cpack, seconds) and
# installed in the image with dpkg on a root that has deploy/install-deps.sh
# --runtime-only's packages alone, so the stage costs no second compile and
# the .debs install on a clean Debian root; the release target's build stage
# is the same install script, CMake flags and cpack. The run-time list and
# the .debs' Depends must agree both ways: dpkg refuses a Depends the list
# lacks, and a package of the list that neither .deb needs (apt's
# autoremove, with the list marked automatic) fails the stage.
# python3-visq and libvisq-client-dev install each on a clean
# debian:bookworm-slim of its own (their Depends from the mirror, in a layer
# podman caches): the Python package answers Health, and a find_package and
# a pkg-config consumer build against the -dev package and answer.
# The debian:bookworm base comes from the local podman store, else from a
# tarball cached in $VISQ_CI_CACHE (default /var/cache/visq-ci), else
# debootstrap makes it once (minutes) and caches it. The runtime stage's apt
# layer is cached by podman, so a rerun rebuilds only the packages' layer.
#
# The container runs as the Kubernetes pods do: the image's user, a
# read-only root filesystem (tmpfs /tmp), every capability dropped, no new
# privileges, shader caches on /tmp. --network host, because this machine has no container network
# plugins; the server listens on a port of its choosing on 127.0.0.1.
#
# Exit status: 0 passed; 1 failed (the image does not build, start, serve or
# answer); 77 skipped because this machine cannot build or run containers,
# after one line "visq: container stage skipped: WHY".
# VISQ_TEST_CONTAINER=required turns a skip into a failure (for machines
# that must run it).
#
# VISQ_CONTAINER_TARGET=runtime builds the release image instead, as a
# studio would (`podman build -f deploy/Dockerfile .`): the build stage
# installs the dependencies and compiles visq inside the image from this
# source tree (about as long as the Release build; not part of CI), and the
# same checks run on it.
set -euo pipefail
export LC_ALL=C

if [[ $# -ne 1 || ! -d "$1" ]]; then
  echo "usage: $0 BUILD_DIR (a built visq build directory)" >&2
  exit 2
fi
source_dir=$(cd "$(dirname "$0")/../.." && pwd)
build=$(cd "$1" && pwd)
cache=${VISQ_CI_CACHE:-/var/cache/visq-ci}
# The Debian mirror for `suite` from this machine's own apt sources (deb822
# .sources stanzas and one-line .list entries): the repository names no
# mirror's host. Empty when the machine has none.
apt_source_for() {
  local suite=$1 found
  # Absent files (no .list, no .sources) are no error: the first match or
  # nothing, and always a zero status (this script runs under set -e).
  found=$(
    {
      awk -v suite="$suite" '
        /^[[:space:]]*$/ { if (uri != "" && found) { print uri; exit } uri = ""; found = 0; next }
        /^URIs:/ { uri = $2 }
        /^Suites:/ { for (i = 2; i <= NF; ++i) if ($i == suite) found = 1 }
        END { if (uri != "" && found) print uri }' /etc/apt/sources.list.d/*.sources
      awk -v suite="$suite" '$1 == "deb" {
          for (i = 2; i <= NF; ++i) if ($i ~ /^[a-z]+:\/\//) { if ($(i + 1) == suite) print $i; break } }' \
        /etc/apt/sources.list /etc/apt/sources.list.d/*.list
    } 2>/dev/null || true
  )
  printf '%s\n' "${found%%$'\n'*}"
}
mirror=${VISQ_DEBIAN_MIRROR:-$(apt_source_for bookworm)}
security_mirror=${VISQ_DEBIAN_SECURITY_MIRROR:-$(apt_source_for bookworm-security)}
security_mirror=${security_mirror:-${mirror%/debian}/debian-security}
base=debian:bookworm
target=${VISQ_CONTAINER_TARGET:-runtime-prebuilt}
[[ "$target" == runtime-prebuilt || "$target" == runtime ]] ||
  { echo "VISQ_CONTAINER_TARGET: runtime-prebuilt (the default) or runtime, not '$target'" >&2; exit 2; }
image=localhost/visq:ci-test
[[ "$target" == runtime ]] && image=localhost/visq:release-check
python_image=localhost/visq-python:ci-test
dev_image=localhost/visq-dev:ci-test
scene=cornell_box_visq

skip() {
  echo "visq: container stage skipped: $*"
  if [[ "${VISQ_TEST_CONTAINER:-}" == required ]]; then
    echo "visq: VISQ_TEST_CONTAINER=required: a skipped container stage fails" >&2
    exit 1
  fi
  exit 77
}
fail() {
  echo "visq: container stage FAILED: $*" >&2
  exit 1
}
now() { date +%s.%N; }
since() { awk -v a="$1" -v b="$(now)" 'BEGIN { printf "%.2f", b - a }'; }

server_bin="$build/server/visq-server"
cli_bin="$build/client/cli/visq"
for bin in "$server_bin" "$cli_bin"; do
  [[ -x "$bin" ]] || fail "$bin is not built (cmake --build $build --target visq-server visq)"
done
[[ -f "$build/CPackConfig.cmake" ]] || fail "$build has no CPackConfig.cmake (configure it again: cmake/Package.cmake)"
command -v dpkg-shlibdeps > /dev/null || fail "no dpkg-shlibdeps (dpkg-dev) to give the .debs their Depends"

# --- What this machine can do ----------------------------------------------
command -v podman > /dev/null || skip "podman is not installed (deploy/install-deps.sh installs it)"
command -v runc > /dev/null || command -v crun > /dev/null ||
  skip "no OCI runtime: neither runc nor crun is installed"
if [[ $(id -u) != 0 ]] && ! podman unshare true > /dev/null 2>&1; then
  skip "rootless podman cannot make a user namespace here ($(podman unshare true 2>&1 | head -n 1))"
fi
# Limits runc can set here: podman's defaults (2^20 files, and a process
# limit near the host's) are refused where the hard limits are lower or
# runc may not raise them ("error setting rlimit type 7", "type 6"). The
# host's hard file limit fits; 4096 processes for the container's user is
# far more than visq-server's threads (workers, gRPC, llvmpipe, Embree).
nofile=$(ulimit -Hn)
[[ "$nofile" == unlimited || "$nofile" -gt 1048576 ]] && nofile=1048576
nproc=$(ulimit -Hu)
[[ "$nproc" == unlimited || "$nproc" -gt 4096 ]] && nproc=4096
limits=(--ulimit "nofile=$nofile:$nofile" --ulimit "nproc=$nproc:$nproc")

tmp=$(mktemp -d)
container=visq-ci-test-$$
cleanup() {
  podman rm --force --volumes --time 0 "$container" > /dev/null 2>&1 || true
  rm -rf "$tmp"
}
trap cleanup EXIT

# --- The base image: once per machine ----------------------------------------
start=$(now)
base_how=reused
if ! podman image exists "$base"; then
  tarball="$cache/debian-bookworm-minbase.tar"
  if [[ ! -f "$tarball" ]]; then
    command -v debootstrap > /dev/null ||
      skip "no $base image and no debootstrap to make one (deploy/install-deps.sh installs it)"
    [[ $(id -u) == 0 ]] || skip "no $base image, and debootstrap needs root to make one"
    mkdir -p "$cache" || skip "cannot write the base image cache $cache (set VISQ_CI_CACHE)"
    rootfs="$cache/rootfs.tmp"
    rm -rf "$rootfs"
    [[ -n $mirror ]] ||
      skip "no Debian mirror for bookworm in this machine's apt sources to make $base from (set VISQ_DEBIAN_MIRROR)"
    echo "visq: making the $base base image with debootstrap from $mirror (once; cached in $cache)"
    if ! debootstrap --variant=minbase bookworm "$rootfs" "$mirror" > "$tmp/debootstrap.log" 2>&1; then
      rm -rf "$rootfs"
      skip "debootstrap could not make $base from $mirror (no network to the mirror?): $(tail -n 1 "$tmp/debootstrap.log")"
    fi
    # The sources of the official image (updates and security too), so the
    # runtime stage installs the versions the host built against.
    rm -f "$rootfs/etc/apt/sources.list"
    cat > "$rootfs/etc/apt/sources.list.d/debian.sources" << EOF
Types: deb
URIs: $mirror
Suites: bookworm bookworm-updates
Components: main
Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg

Types: deb
URIs: $security_mirror
Suites: bookworm-security
Components: main
Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg
EOF
    rm -rf "$rootfs"/var/cache/apt/archives/*.deb "$rootfs"/var/lib/apt/lists/*
    tar --numeric-owner -C "$rootfs" -cf "$tarball.tmp" . && mv "$tarball.tmp" "$tarball"
    rm -rf "$rootfs"
    base_how="made by debootstrap"
  else
    base_how="imported from $tarball"
  fi
  podman import --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
    --change 'CMD ["bash"]' "$tarball" "$base" > "$tmp/import.log" 2>&1 ||
    skip "podman cannot store an image here (importing the debootstrap root failed): $(tail -n 1 "$tmp/import.log")"
fi
# The runtime stage starts from the slim tag; here both are the same image.
podman image exists "$base-slim" || podman tag "$base" "$base-slim"
base_s=$(since "$start")

# A machine that has podman but cannot run containers (no cgroups, a
# seccomp or AppArmor policy that forbids it, a nested sandbox) says so here.
if ! podman run --rm --pull=never --network host "${limits[@]}" "$base" true > "$tmp/probe.log" 2>&1; then
  skip "podman cannot run a container here: $(grep -m 1 -i error "$tmp/probe.log" || head -n 1 "$tmp/probe.log")"
fi

# --- The .debs, then the image around them -------------------------------------
start=$(now)
(cd "$build" && cpack -G DEB -B "$tmp/packages") > "$tmp/cpack.log" 2>&1 ||
  { tail -n 20 "$tmp/cpack.log" >&2
    fail "cpack could not make the four .debs" \
      "(cmake --build $build --target visq-server visq visq_client visq_proto visq_python_stubs)"; }
server_deb=$(ls "$tmp/packages"/visq-server_*.deb 2> /dev/null) || fail "cpack made no visq-server .deb: $(tail -n 3 "$tmp/cpack.log")"
client_deb=$(ls "$tmp/packages"/visq-client_*.deb 2> /dev/null) || fail "cpack made no visq-client .deb: $(tail -n 3 "$tmp/cpack.log")"
python_deb=$(ls "$tmp/packages"/python3-visq_*.deb 2> /dev/null) || fail "cpack made no python3-visq .deb: $(tail -n 3 "$tmp/cpack.log")"
dev_deb=$(ls "$tmp/packages"/libvisq-client-dev_*.deb 2> /dev/null) ||
  fail "cpack made no libvisq-client-dev .deb: $(tail -n 3 "$tmp/cpack.log")"
pack_s=$(since "$start")
# A context of its own, three files: the build reads nothing else. The
# release target's is the source tree, whose build stage compiles it.
context=$tmp/context
if [[ "$target" == runtime ]]; then
  context=$source_dir
else
  mkdir -p "$tmp/context/deploy" "$tmp/context/prebuilt"
  cp "$source_dir/deploy/install-deps.sh" "$tmp/context/deploy/"
  cp "$server_deb" "$tmp/context/prebuilt/visq-server.deb"
  cp "$client_deb" "$tmp/context/prebuilt/visq-client.deb"
fi
old_image=$(podman image inspect --format '{{.Id}}' "$image" 2> /dev/null || true)
start=$(now)
# --format docker keeps the Dockerfile's HEALTHCHECK (OCI images drop it).
if ! podman build --pull=never --network host "${limits[@]}" --format docker --target "$target" \
    -f "$source_dir/deploy/Dockerfile" -t "$image" "$context" > "$tmp/build.log" 2>&1; then
  # The runtime stage installs its libraries with apt-get: without the
  # mirror (and without the layer in the cache) the image cannot build here.
  if grep -qE "Temporary failure resolving|Could not resolve|Failed to fetch|Unable to connect" "$tmp/build.log"; then
    skip "the image's apt-get cannot reach the Debian mirror: $(grep -m 1 -E 'resolv|fetch|connect' "$tmp/build.log")"
  fi
  tail -n 30 "$tmp/build.log" >&2
  if grep -q "dependency problems" "$tmp/build.log"; then
    fail "dpkg refused the .debs on a root with install-deps.sh --runtime-only's packages: add what the" \
      "'depends on' lines above name to runtime_packages in deploy/install-deps.sh"
  fi
  fail "podman build of deploy/Dockerfile (target $target) failed; the log's end is above"
fi
build_s=$(since "$start")
new_image=$(podman image inspect --format '{{.Id}}' "$image")
# Each run's packages are a new layer: drop the previous run's image.
if [[ -n "$old_image" && "$old_image" != "$new_image" ]]; then podman image rm "$old_image" > /dev/null 2>&1 || true; fi

# The other way round: every package of the run-time list is one the .debs
# need (Depends or Recommends, directly or through another package). With
# the list marked automatically installed, apt's autoremove would take
# exactly the packages nothing else needs.
mapfile -t runtime_list < <(bash "$source_dir/deploy/install-deps.sh" --runtime-only --print)
podman run --rm --pull=never --network host "${limits[@]}" --user root --entrypoint /bin/sh "$image" -c \
  'apt-mark auto "$@" > /dev/null && apt-get -s autoremove && dpkg-query -W visq-server visq-client' \
  sh "${runtime_list[@]}" > "$tmp/autoremove.log" 2>&1 ||
  { cat "$tmp/autoremove.log" >&2; fail "apt-get -s autoremove in the image failed"; }
unneeded=$(awk 'NR == FNR { listed[$1] = 1; next } $1 == "Remv" && ($2 in listed) { print $2 }' \
  <(printf '%s\n' "${runtime_list[@]}") "$tmp/autoremove.log" | sort | tr '\n' ' ')
[[ -z "$unneeded" ]] || fail "install-deps.sh --runtime-only lists packages neither .deb needs: $unneeded"
installed=$(awk '$1 ~ /^visq-(server|client)$/ { printf "%s%s %s", sep, $1, $2; sep = ", " }' "$tmp/autoremove.log")

# --- Run it as the pods do ---------------------------------------------------
# The image's defaults (seeded sample scenes, a token made in the volume),
# except the address: a port of the server's choosing on loopback.
start=$(now)
# --no-healthcheck: the image's HEALTHCHECK asks port 50051, and podman
# would schedule it through systemd; the same command runs below, on the
# server's port.
podman run -d --name "$container" --pull=never --network host "${limits[@]}" --no-healthcheck \
  --read-only --cap-drop ALL --security-opt no-new-privileges \
  -e VISQ_ADDRESS=127.0.0.1:0 -e VISQ_PORT_FILE=/tmp/visq-port -e XDG_CACHE_HOME=/tmp/cache "$image" > /dev/null ||
  fail "podman run $image failed"
logs() { podman logs "$container" 2>&1 | tail -n 40 >&2; }
port=
serving=0
for ((i = 0; i < 1200; ++i)); do  # up to two minutes
  if [[ $(podman inspect --format '{{.State.Running}}' "$container") != true ]]; then
    logs
    fail "the container stopped before it served (exit $(podman inspect --format '{{.State.ExitCode}}' "$container")); its log is above"
  fi
  [[ -z "$port" ]] && port=$(podman exec "$container" cat /tmp/visq-port 2> /dev/null || true)
  if [[ -n "$port" ]] && "$cli_bin" health --server "127.0.0.1:$port" --timeout 2 > /dev/null 2>&1; then
    serving=1
    break
  fi
  sleep 0.1
done
(( serving )) || { logs; fail "health did not report SERVING within two minutes; the log is above"; }
serving_s=$(since "$start")
server=127.0.0.1:$port
# The HEALTHCHECK's command, with the image's own CLI: its libraries are there.
healthcheck=$(podman image inspect --format '{{json .Config.Healthcheck}}' "$image")
[[ "$healthcheck" == *'"/usr/bin/visq","health"'* ]] ||
  fail "the image has no HEALTHCHECK running visq health (built without --format docker?)"
podman exec "$container" /usr/bin/visq health --server "$server" > /dev/null ||
  fail "the image's visq health does not report SERVING"

# The token, as the Dockerfile's comment says to fetch it.
podman cp "$container:/var/lib/visq/scenes/.visq-auth-token" "$tmp/token" ||
  { logs; fail "no token in the volume at /var/lib/visq/scenes/.visq-auth-token"; }
# To a file first: grep -q stops reading at the match, and under pipefail
# the writer's SIGPIPE would fail the check.
podman logs "$container" > "$tmp/server.log" 2>&1
grep -q "/var/lib/visq/scenes/.visq-auth-token" "$tmp/server.log" ||
  { logs; fail "the log does not say where the token is; the log is above"; }
if "$cli_bin" list --server "$server" > "$tmp/denied.log" 2>&1; then
  fail "visq list without the token was answered: the image's defaults must require it"
fi
grep -q UNAUTHENTICATED "$tmp/denied.log" || fail "visq list without the token: $(cat "$tmp/denied.log")"

# One real query on the seeded sample scene: the ceiling light's visibility
# from the floor, which the two boxes shade in part.
start=$(now)
# visq-client's CLI, in the image, with the token where the image keeps it.
podman exec "$container" /usr/bin/visq list --server "$server" --token-file /var/lib/visq/scenes/.visq-auth-token \
  > "$tmp/list.log" 2>&1 || fail "the image's visq list: $(cat "$tmp/list.log")"
grep -q "^$scene " "$tmp/list.log" || fail "the seeded scene $scene is not listed: $(cat "$tmp/list.log")"
"$cli_bin" hidden-map --server "$server" --token-file "$tmp/token" --scene "$scene" \
  --source "-0.25,1.99,-0.25;0.5,0,0;0,0,0.5" --receiver "-0.999,0.001,-0.999;1.998,0,0;0,0,1.998" \
  --samples 64 --width 32 --height 32 > "$tmp/query.log" 2>&1 || fail "visq hidden-map: $(cat "$tmp/query.log")"
mean=$(sed -n 's/.*mean visible fraction \([0-9.]*\).*/\1/p' "$tmp/query.log")
awk -v m="$mean" 'BEGIN { exit !(m > 0 && m < 1) }' ||
  fail "the hidden-sample map's mean visible fraction is '$mean', not inside (0, 1): $(cat "$tmp/query.log")"
query_s=$(since "$start")
gpu=$("$cli_bin" stats --server "$server" --token-file "$tmp/token" | sed -n 's/^GPU *//p')

# python3-visq and libvisq-client-dev, each on a clean Debian root of its
# own: debian:bookworm-slim, the names the .deb gives (its Depends, and for
# the -dev package the build tools it suggests) from the mirror with apt in
# a layer podman caches (the layer changes only when the names do), then
# the .deb with dpkg, which refuses it if a Depends is missing.
#   clean_root_image TAG DEB FIELDS...: builds TAG.
clean_root_image() {
  local tag=$1 deb=$2 context old new packages field
  shift 2
  context=$tmp/context-$(basename "$deb" .deb)
  mkdir -p "$context"
  cp "$deb" "$context/package.deb"
  packages=$(for field in "$@"; do dpkg-deb -f "$deb" "$field"; echo; done | tr ',' '\n' |
    sed 's/(.*)//; s/|.*//; s/^ *//; s/ *$//' | sed '/^$/d' | sort -u | tr '\n' ' ')
  cat > "$context/Containerfile" << 'CONTAINERFILE'
FROM debian:bookworm-slim
ARG PACKAGES
RUN apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends $PACKAGES \
 && rm -rf /var/lib/apt/lists/*
COPY package.deb /tmp/
RUN dpkg -i /tmp/package.deb && rm /tmp/package.deb
CONTAINERFILE
  old=$(podman image inspect --format '{{.Id}}' "$tag" 2> /dev/null || true)
  if ! podman build --pull=never --network host "${limits[@]}" --build-arg "PACKAGES=$packages" \
      -t "$tag" "$context" > "$context/build.log" 2>&1; then
    tail -n 30 "$context/build.log" >&2
    if grep -qE "Temporary failure resolving|Could not resolve|Failed to fetch|Unable to connect" "$context/build.log"; then
      skip "apt-get cannot reach the Debian mirror for $(basename "$deb")'s Depends:" \
        "$(grep -m 1 -E 'resolv|fetch|connect' "$context/build.log")"
    fi
    fail "$(basename "$deb") did not install on a clean debian:bookworm-slim (apt-get install $packages, then dpkg -i)"
  fi
  new=$(podman image inspect --format '{{.Id}}' "$tag")
  if [[ -n "$old" && "$old" != "$new" ]]; then podman image rm "$old" > /dev/null 2>&1 || true; fi
}
token_value=$(head -n 1 "$tmp/token")

# python3-visq: import visq (the stubs from the package, no protoc there)
# and ask the image's server for Health and the scenes.
start=$(now)
clean_root_image "$python_image" "$python_deb" Depends
podman run --rm --pull=never --network host "${limits[@]}" -e VISQ_TOKEN="$token_value" "$python_image" \
  python3 -c 'import os, sys, visq
assert visq.__file__.startswith("/usr/lib/python3/dist-packages/visq/"), visq.__file__
with visq.Client(sys.argv[1], token=os.environ["VISQ_TOKEN"]) as c:
    print("health", c.health())
    print("scenes", " ".join(s.name for s in c.list_scenes()))' "$server" > "$tmp/python.log" 2>&1 ||
  fail "python3-visq in a clean root: $(cat "$tmp/python.log")"
grep -qx "health SERVING" "$tmp/python.log" && grep -q "^scenes.* $scene" "$tmp/python.log" ||
  fail "python3-visq in a clean root: $(cat "$tmp/python.log")"
python_s=$(since "$start")

# libvisq-client-dev: tests/install/consumer built with find_package(visq)
# and with pkg-config visq-client, both run against the image's server.
start=$(now)
clean_root_image "$dev_image" "$dev_deb" Depends Suggests
podman run --rm --pull=never --network host "${limits[@]}" -e VISQ_TOKEN="$token_value" \
  -v "$source_dir/tests/install/consumer:/consumer:ro" "$dev_image" sh -ec '
    cp -r /consumer /tmp/consumer
    cmake -S /tmp/consumer -B /tmp/build -DCMAKE_FIND_USE_PACKAGE_REGISTRY=OFF > /tmp/log 2>&1 || { cat /tmp/log; exit 1; }
    grep -qx "visq_DIR:PATH=/usr/lib/cmake/visq" /tmp/build/CMakeCache.txt ||
      { echo "find_package(visq): $(grep ^visq_DIR /tmp/build/CMakeCache.txt)"; exit 1; }
    cmake --build /tmp/build > /tmp/log 2>&1 || { cat /tmp/log; exit 1; }
    c++ -std=c++17 -O0 /tmp/consumer/main.cpp $(pkg-config --cflags --libs visq-client) -o /tmp/consumer_pkg_config
    /tmp/build/visq_consumer "$1"
    /tmp/consumer_pkg_config "$1"' sh "$server" > "$tmp/dev.log" 2>&1 ||
  fail "libvisq-client-dev in a clean root: $(cat "$tmp/dev.log")"
[[ $(grep -cx "health SERVING" "$tmp/dev.log") == 2 && $(grep -c "^scene $scene [1-9]" "$tmp/dev.log") == 2 ]] ||
  fail "libvisq-client-dev in a clean root: $(cat "$tmp/dev.log")"
dev_s=$(since "$start")

# A clean stop: SIGTERM, the drain, exit 0.
start=$(now)
podman stop --time 30 "$container" > /dev/null
stop_s=$(since "$start")
code=$(podman inspect --format '{{.State.ExitCode}}' "$container")
[[ "$code" == 0 ]] || { logs; fail "the server exited $code on SIGTERM, not 0; the log is above"; }

echo "visq: container stage passed (target $target): base image ${base_s} s ($base_how), .debs ${pack_s} s" \
  "($installed: their Depends and install-deps.sh --runtime-only agree), image build ${build_s} s," \
  "SERVING ${serving_s} s after podman run, list + hidden-map ${query_s} s (mean visible fraction $mean)," \
  "python3-visq on a clean root ${python_s} s, libvisq-client-dev on a clean root and two consumers ${dev_s} s," \
  "stop ${stop_s} s; GPU: $gpu"
