#!/usr/bin/env bash
# Set up one Python environment (idempotent; reused on later runs):
#
#   bash scripts/env.sh runtime   .venv      Python 3.13, bpy 5.2 LTS + scipy (requirements.txt): the demo
#   bash scripts/env.sh dev       .venv      the same + pytest (requirements-dev.txt): tests, build
#   bash scripts/env.sh 4.5       .venv-4.5  Python 3.11, bpy 4.5 LTS (requirements-4.5.txt): the
#                                            second Blender the tests run on
#
# Each requirements file is installed again only when it changed.  The Python
# comes from $PYTHON313 / $PYTHON311, else python3.X on PATH, else pyenv; if
# none is found the script stops with one line saying what to install.
# Building the extension zips is scripts/build_extension.sh (`make extension`).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
WHAT="${1:-dev}"
case "$WHAT" in
  runtime) VENV="$ROOT/.venv"; WANT_PY=3.13; REQS=(requirements.txt) ;;
  dev)     VENV="$ROOT/.venv"; WANT_PY=3.13; REQS=(requirements.txt requirements-dev.txt) ;;
  4.5)     VENV="$ROOT/.venv-4.5"; WANT_PY=3.11; REQS=(requirements-4.5.txt) ;;
  *) echo "env: unknown environment '$WHAT' (runtime, dev or 4.5)" >&2; exit 2 ;;
esac
PY="$VENV/bin/python"
VAR="PYTHON${WANT_PY/./}"   # PYTHON313 / PYTHON311

is_python() {  # is_python CMD... : runs and is Python $WANT_PY
  "$@" -c "import sys; raise SystemExit(sys.version_info[:2] != tuple(map(int, '$WANT_PY'.split('.'))))" \
    >/dev/null 2>&1
}

find_python() {  # prints a path to a working python$WANT_PY
  local c
  if [ -n "${!VAR:-}" ]; then
    is_python "${!VAR}" && { echo "${!VAR}"; return 0; }
    echo "env: \$$VAR=${!VAR} is not a working Python $WANT_PY" >&2; return 1
  fi
  # On PATH (a pyenv shim refuses unless that version is selected: then it fails here).
  if c="$(command -v "python$WANT_PY")" && is_python "$c"; then echo "$c"; return 0; fi
  # pyenv, without selecting the version globally.
  if command -v pyenv >/dev/null 2>&1; then
    for c in "$(pyenv root)"/versions/"$WANT_PY".*/bin/"python$WANT_PY"; do
      [ -x "$c" ] && is_python "$c" && { echo "$c"; return 0; }
    done
  fi
  return 1
}

STAMP="$VENV/.artdef-$WHAT.sha256"
WANT="$(cat "${REQS[@]}" | sha256sum | cut -d' ' -f1)"

free_mb() {  # free_mb DIR : megabytes free on DIR's file system
  df -Pk "$1" 2>/dev/null | awk 'NR == 2 { print int($4 / 1024) }'
}

# An install (bpy: a ~400 MB wheel that unpacks to ~1.1 GB; the venv ends at ~1.2 GB) on a full disk fails half-way in
# pip; say so up front, before anything is created.
if ! { [ -x "$PY" ] && is_python "$PY" && [ "$(cat "$STAMP" 2>/dev/null || true)" = "$WANT" ]; }; then
  NEED_MB="${ARTDEF_ENV_NEED_MB:-1600}"
  for DIR in "$ROOT" "${TMPDIR:-/tmp}"; do
    HAVE_MB="$(free_mb "$DIR")"
    if [ -n "$HAVE_MB" ] && [ "$HAVE_MB" -lt "$NEED_MB" ]; then
      echo "env: only $HAVE_MB MB free on the disk of $DIR; setting up ${VENV#$ROOT/} needs about $NEED_MB MB: free some space and run again" >&2
      exit 1
    fi
  done
fi

if [ -x "$PY" ] && is_python "$PY"; then
  echo "env: reusing ${VENV#$ROOT/} ($("$PY" --version))"
else
  BASE="$(find_python)" || {
    echo "env: Python $WANT_PY not found: install it (e.g. 'pyenv install $WANT_PY', or your" \
         "distribution's python$WANT_PY and python$WANT_PY-venv) or set $VAR=/path/to/python$WANT_PY" >&2
    exit 3; }
  echo "env: creating ${VENV#$ROOT/} with $BASE"
  rm -rf "$VENV"
  "$BASE" -m venv "$VENV" || {
    echo "env: '$BASE -m venv' failed; on Debian: apt-get install python$WANT_PY-venv" >&2; exit 1; }
fi

if [ "$(cat "$STAMP" 2>/dev/null || true)" != "$WANT" ]; then
  echo "env: installing ${REQS[*]} into ${VENV#$ROOT/}"
  "$PY" -m pip install --disable-pip-version-check -q -r "${REQS[-1]}"
  echo "$WANT" > "$STAMP"
else
  echo "env: ${REQS[-1]} already installed in ${VENV#$ROOT/}"
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
