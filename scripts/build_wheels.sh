#!/usr/bin/env bash
# Download the scipy wheels that the extension bundles (listed in
# blender_manifest.toml) into wheels/.  Idempotent: a wheel already present is
# not downloaded again.  numpy is never bundled (--no-deps): Blender ships its
# own and a bundled copy would shadow it.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
PY="${PYTHON:-$ROOT/.venv/bin/python}"
[ -x "$PY" ] || PY="$(command -v python3.11 || command -v python3)"
SCIPY_VERSION=1.15.3
mkdir -p wheels

# platform tag given to pip | file name the manifest expects
WHEELS=(
  "manylinux2014_x86_64 manylinux_2_17_x86_64|scipy-${SCIPY_VERSION}-cp311-cp311-manylinux_2_17_x86_64.manylinux2014_x86_64.whl"
  "win_amd64|scipy-${SCIPY_VERSION}-cp311-cp311-win_amd64.whl"
  "macosx_12_0_arm64|scipy-${SCIPY_VERSION}-cp311-cp311-macosx_12_0_arm64.whl"
  "macosx_10_13_x86_64|scipy-${SCIPY_VERSION}-cp311-cp311-macosx_10_13_x86_64.whl"
)

for entry in "${WHEELS[@]}"; do
  platforms="${entry%%|*}"
  file="${entry##*|}"
  if [ -s "wheels/$file" ]; then
    echo "build_wheels: have $file"
    continue
  fi
  # Every wheel the manifest lists must be here, or the build drops it silently.
  grep -q "./wheels/$file" blender_manifest.toml || {
    echo "build_wheels: $file is not listed in blender_manifest.toml" >&2; exit 1; }
  args=()
  for p in $platforms; do args+=(--platform "$p"); done
  tmp="$(mktemp -d)"
  "$PY" -m pip download --disable-pip-version-check -q --only-binary=:all: --no-deps \
    --python-version 3.11 --implementation cp "${args[@]}" \
    -d "$tmp" "scipy==${SCIPY_VERSION}"
  if [ ! -s "$tmp/$file" ]; then
    echo "build_wheels: expected $file, pip gave: $(ls "$tmp")" >&2
    rm -rf "$tmp"; exit 1
  fi
  mv "$tmp/$file" "wheels/$file"
  rm -rf "$tmp"
  echo "build_wheels: downloaded $file"
done
