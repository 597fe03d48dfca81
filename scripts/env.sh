#!/usr/bin/env bash
# Shared set-up for scripts/demo.sh and scripts/test.sh (sourced, or run alone):
#   1. create .venv with Python 3.11 if missing (reused on later runs),
#   2. install requirements-dev.txt (skipped when unchanged since last install),
#   3. check that the bpy module loads (and name the Debian packages if not),
#   4. download the bundled wheels and build the extension zips into dist/.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
VENV="$ROOT/.venv"
PY="$VENV/bin/python"

find_python311() {
  for c in "${PYTHON311:-}" python3.11 python3; do
    [ -n "$c" ] || continue
    if command -v "$c" >/dev/null 2>&1 &&
       "$c" -c 'import sys; raise SystemExit(sys.version_info[:2] != (3, 11))' 2>/dev/null; then
      command -v "$c"; return 0
    fi
  done
  return 1
}

if [ ! -x "$PY" ] || ! "$PY" -c 'import sys; raise SystemExit(sys.version_info[:2] != (3, 11))' 2>/dev/null; then
  PY311="$(find_python311)" || {
    echo "env: Python 3.11 is required (bpy 5.0 is built for it); install python3.11 or set PYTHON311=/path/to/python3.11" >&2
    exit 1; }
  echo "env: creating .venv with $PY311"
  rm -rf "$VENV"
  "$PY311" -m venv "$VENV" || {
    echo "env: 'python3.11 -m venv' failed; on Debian: apt-get install python3.11-venv" >&2; exit 1; }
else
  echo "env: reusing .venv ($("$PY" --version))"
fi

STAMP="$VENV/.artdef-requirements.sha256"
WANT="$(sha256sum requirements-dev.txt | cut -d' ' -f1)"
if [ "$(cat "$STAMP" 2>/dev/null || true)" != "$WANT" ]; then
  echo "env: installing requirements-dev.txt"
  "$PY" -m pip install --disable-pip-version-check -q -r requirements-dev.txt
  echo "$WANT" > "$STAMP"
else
  echo "env: requirements-dev.txt already installed"
fi

# bpy links against a few X11/GL client libraries even when run headless.
if ! err="$("$PY" -c 'import bpy' 2>&1)"; then
  DEBS="libx11-6 libxrender1 libxfixes3 libxi6 libxext6 libxkbcommon0 libxxf86vm1 libsm6 libice6 libgl1 libegl1"
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    echo "env: bpy failed to load ($(echo "$err" | tail -1)); installing $DEBS"
    apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q $DEBS
    "$PY" -c 'import bpy'
  else
    echo "env: bpy failed to load: $(echo "$err" | tail -1)" >&2
    echo "env: install the libraries it needs: sudo apt-get install $DEBS" >&2
    exit 1
  fi
fi

bash scripts/build_extension.sh
