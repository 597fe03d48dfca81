#!/usr/bin/env bash
# The demo command: set up the environment (idempotent), build the extension,
# fit the bundled sample (rod by default; `bash scripts/demo.sh branching 4`
# for the other one) and write out/: result .npz, .blend, .glb, .png.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
SAMPLE="${1:-rod}"
LINKS="${2:-3}"
bash scripts/env.sh
bash scripts/install_validator.sh
PY="$ROOT/.venv/bin/python"

mkdir -p out
"$PY" -m artdef_addon sample "$SAMPLE" -o out/scan.npz
"$PY" -m artdef_addon fit out/scan.npz --links "$LINKS" -o out/result.npz \
  --blend out/demo.blend --glb out/demo.glb --png out/demo.png

echo
if [ -f .tools/node_modules/gltf-validator/package.json ]; then
  node scripts/validate_gltf.js out/demo.glb
else
  echo "demo: gltf-validator not installed: out/demo.glb not validated"
fi
echo "demo: wrote"
ls -l out/scan.npz out/result.npz out/demo.blend out/demo.glb out/demo.png
echo "demo: extension zips (drag one into Blender 4.2+ to install):"
ls -l dist/artdef-*.zip
