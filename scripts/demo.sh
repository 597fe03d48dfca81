#!/usr/bin/env bash
# The demo command: set up the environment (idempotent), build the extension,
# fit the bundled sample and write out/ (result .npz, .blend, .glb, .png).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
bash scripts/env.sh
PY="$ROOT/.venv/bin/python"
SAMPLE="${1:-rod}"

mkdir -p out
"$PY" -m artdef_addon sample "$SAMPLE" -o out/scan.npz
"$PY" -m artdef_addon fit out/scan.npz --links 3 -o out/result.npz \
  --blend out/demo.blend --glb out/demo.glb --png out/demo.png
echo
echo "demo: wrote"
ls -l out/scan.npz out/result.npz out/demo.blend out/demo.glb out/demo.png
echo "demo: extension zips in dist/:"
ls -l dist/artdef-*.zip
