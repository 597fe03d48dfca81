#!/usr/bin/env bash
# Install the Khronos glTF validator (npm package gltf-validator, compiled from
# KhronosGroup/glTF-Validator) into .tools/.  Idempotent.  Without node/npm it
# says so and exits 0: the callers then skip validation.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VERSION=2.0.0-dev.3.10
PKG="$ROOT/.tools/node_modules/gltf-validator/package.json"
if [ -f "$PKG" ] && grep -q "\"version\": \"$VERSION\"" "$PKG"; then
  echo "validator: gltf-validator $VERSION already in .tools/"
elif command -v npm >/dev/null 2>&1 && command -v node >/dev/null 2>&1; then
  echo "validator: installing gltf-validator $VERSION into .tools/"
  npm install --prefix "$ROOT/.tools" --no-audit --no-fund --loglevel=error \
    "gltf-validator@$VERSION"
else
  echo "validator: node/npm not found: glTF validation will be SKIPPED (Debian: apt-get install nodejs npm)"
fi
