#!/usr/bin/env bash
# Build dist/artdef-<version>-<platform>.zip (one per platform, each with only
# its own scipy wheels: cp311 and cp313) with Blender's own extension builder, taken from the bpy
# module, then validate each zip.  Needs the venv (bpy) and wheels/.
# ARTDEF_DIST=<dir> builds into another directory (the tests use a private one
# so that concurrent test runs never see a half-written dist/).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
PY="${PYTHON:-$ROOT/.venv/bin/python}"

bash scripts/build_wheels.sh

BLENDER_EXT="$("$PY" - <<'PYEOF'
import glob, importlib.util, os
spec = importlib.util.find_spec("bpy")
if spec is None or not spec.submodule_search_locations:
    raise SystemExit("build_extension: the bpy module is not installed in this Python")
base = list(spec.submodule_search_locations)[0]
hits = sorted(glob.glob(os.path.join(base, "*", "scripts", "addons_core", "bl_pkg", "cli", "blender_ext.py")))
if not hits:
    raise SystemExit("build_extension: blender_ext.py not found under " + base)
print(hits[-1])
PYEOF
)"

OUT="${ARTDEF_DIST:-dist}"
mkdir -p "$OUT"

start=$(date +%s)
"$PY" "$BLENDER_EXT" build --source-dir . --output-dir "$OUT" --split-platforms
for z in "$OUT"/artdef-*.zip; do
  "$PY" "$BLENDER_EXT" validate "$z"
done
echo "build_extension: built in $(( $(date +%s) - start )) s:"
ls -l "$OUT"/artdef-*.zip
