#!/usr/bin/env bash
# install_validator.sh SOURCE_DIR DEST_DIR
# Installs npm's gltf-validator, pinned by SOURCE_DIR/package-lock.json, into
# DEST_DIR/node_modules with `npm ci` (from the registry npm is configured
# with), unless DEST_DIR already holds that lock's install. The
# visq_gltf_validator_install fixture runs it before the export tests.
# Without npm it says so and succeeds: the tests then skip, saying so too.
set -euo pipefail
source_dir=$1 dest=$2
if ! command -v npm >/dev/null; then
  echo "npm is absent (deploy/install-deps.sh installs nodejs and npm): the glTF validator tests will skip"
  exit 0
fi
mkdir -p "$dest"
if [[ -f "$dest/node_modules/gltf-validator/package.json" ]] && cmp -s "$source_dir/package-lock.json" "$dest/package-lock.json"; then
  echo "gltf-validator already installed in $dest"
  exit 0
fi
cp "$source_dir/package.json" "$source_dir/package-lock.json" "$dest/"
cd "$dest"
# Node trusts its own bundled roots; a machine whose outbound TLS passes
# through its own authority has that authority in the system store.
if [[ -z "${NODE_EXTRA_CA_CERTS:-}" && -r /etc/ssl/certs/ca-certificates.crt ]]; then
  export NODE_EXTRA_CA_CERTS=/etc/ssl/certs/ca-certificates.crt
fi
log=$(mktemp)
trap 'rm -f "$log"' EXIT
if ! npm ci --no-audit --no-fund --loglevel=error > "$log" 2>&1; then
  cat "$log"
  # A registry this machine cannot reach (no network, a proxy it does not
  # trust) is a missing tool, as a missing npm is: the tests skip and say
  # why. Any other failure (a bad lock file, a broken package) fails.
  if grep -qE 'request to .* failed|ENOTFOUND|EAI_AGAIN|ECONNREFUSED|ECONNRESET|ETIMEDOUT|CERT|certificate' "$log"; then
    rm -rf "$dest/node_modules"
    echo "npm's registry cannot be reached from this machine: the glTF validator tests will skip"
    exit 0
  fi
  exit 1
fi
echo "installed gltf-validator $(node -p 'require("gltf-validator/package.json").version') into $dest"
