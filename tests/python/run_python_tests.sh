#!/usr/bin/env bash
# Installs client/python offline into a scratch venv (Debian's grpcio,
# protobuf and numpy seen through --system-site-packages, the stubs generated
# by the system protoc) and runs its tests against the real visq-server.
#   run_python_tests.sh SOURCE_DIR SERVER_BINARY CLI_BINARY
# Exits 77 (ctest: skipped) when /usr/bin/python3 lacks what the package needs.
set -euo pipefail
source_dir=$1 server=$2 cli=$3
python=/usr/bin/python3
missing=()
for module in grpc google.protobuf numpy venv; do
  "$python" -c "import $module" 2>/dev/null || missing+=("$module")
done
for tool in protoc grpc_python_plugin; do
  command -v "$tool" >/dev/null || missing+=("$tool")
done
if (( ${#missing[@]} )); then
  echo "SKIPPED: $python lacks ${missing[*]} (deploy/install-deps.sh installs python3-grpcio," \
       "python3-protobuf, python3-numpy, python3-venv, protobuf-compiler-grpc)"
  exit 77
fi
scratch=$(mktemp -d /tmp/visq-python-XXXXXX)
trap 'rm -rf "$scratch"' EXIT
# A copy, so the in-tree build writes nothing into the checkout.
cp -r "$source_dir/client/python" "$scratch/src"
rm -rf "$scratch/src/build" "$scratch/src"/*.egg-info
"$python" -m venv --system-site-packages "$scratch/venv"
VISQ_PROTO_DIR="$source_dir/proto" "$scratch/venv/bin/pip" install --quiet --no-build-isolation --no-index \
  --disable-pip-version-check "$scratch/src"
cd "$scratch"  # import the installed package, not the source folder
VISQ_SERVER_BINARY=$server VISQ_CLI_BINARY=$cli "$scratch/venv/bin/python" -m unittest discover \
  -s "$scratch/src/tests" -v
