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
npm ci --no-audit --no-fund --loglevel=error
echo "installed gltf-validator $(node -p 'require("gltf-validator/package.json").version') into $dest"
