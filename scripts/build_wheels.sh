#!/usr/bin/env bash
# Download the scipy wheels that the extension bundles (listed in
# blender_manifest.toml) into wheels/: for every platform one wheel for
# Python 3.11 (Blender 4.5 LTS, 5.0) and one for Python 3.13 (Blender 5.1+).
# Idempotent: a wheel already present is not downloaded again.  numpy is never
# bundled (--no-deps): Blender ships its own and a bundled copy would shadow it.
# ARTDEF_PLATFORMS="linux-x64 ..." limits the download to those platforms.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
PY="${PYTHON:-$ROOT/.venv/bin/python}"
[ -x "$PY" ] || PY="$(command -v python3)"
mkdir -p wheels
WANT_PLATFORMS="${ARTDEF_PLATFORMS:-linux-x64 windows-x64 macos-arm64 macos-x64}"

# Blender platform | python | scipy | platform tags given to pip | file the manifest expects
WHEELS=(
  "linux-x64|3.11|1.15.3|manylinux2014_x86_64 manylinux_2_17_x86_64|scipy-1.15.3-cp311-cp311-manylinux_2_17_x86_64.manylinux2014_x86_64.whl"
  "windows-x64|3.11|1.15.3|win_amd64|scipy-1.15.3-cp311-cp311-win_amd64.whl"
  "macos-arm64|3.11|1.15.3|macosx_12_0_arm64|scipy-1.15.3-cp311-cp311-macosx_12_0_arm64.whl"
  "macos-x64|3.11|1.15.3|macosx_10_13_x86_64|scipy-1.15.3-cp311-cp311-macosx_10_13_x86_64.whl"
  "linux-x64|3.13|1.16.3|manylinux2014_x86_64 manylinux_2_17_x86_64|scipy-1.16.3-cp313-cp313-manylinux2014_x86_64.manylinux_2_17_x86_64.whl"
  "windows-x64|3.13|1.16.3|win_amd64|scipy-1.16.3-cp313-cp313-win_amd64.whl"
  "macos-arm64|3.13|1.16.3|macosx_12_0_arm64|scipy-1.16.3-cp313-cp313-macosx_12_0_arm64.whl"
  "macos-x64|3.13|1.16.3|macosx_10_14_x86_64|scipy-1.16.3-cp313-cp313-macosx_10_14_x86_64.whl"
)

for entry in "${WHEELS[@]}"; do
  IFS='|' read -r platform pyver scipy tags file <<<"$entry"
  case " $WANT_PLATFORMS " in *" $platform "*) ;; *) continue ;; esac
  if [ -s "wheels/$file" ]; then
    echo "build_wheels: have $file"
    continue
  fi
  # Every wheel the manifest lists must be here, or the build drops it silently.
  grep -q "./wheels/$file" blender_manifest.toml || {
    echo "build_wheels: $file is not listed in blender_manifest.toml" >&2; exit 1; }
  args=()
  for p in $tags; do args+=(--platform "$p"); done
  tmp="$(mktemp -d)"
  "$PY" -m pip download --disable-pip-version-check -q --only-binary=:all: --no-deps \
    --python-version "$pyver" --implementation cp "${args[@]}" \
    -d "$tmp" "scipy==${scipy}"
  if [ ! -s "$tmp/$file" ]; then
    echo "build_wheels: expected $file, pip gave: $(ls "$tmp")" >&2
    rm -rf "$tmp"; exit 1
  fi
  mv "$tmp/$file" "wheels/$file"
  rm -rf "$tmp"
  echo "build_wheels: downloaded $file"
done
