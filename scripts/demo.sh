#!/usr/bin/env bash
# The demo command: set up only what it needs (idempotent: .venv with the
# runtime requirements, the glTF validator), fit the bundled sample (rod by
# default; `bash scripts/demo.sh branching 4` for the other one) and write out/:
# result .npz, .blend, .glb, .png.  No benchmark packages, no extension zips:
# `make extension` (scripts/build_extension.sh) builds those.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
SAMPLE="${1:-rod}"
LINKS="${2:-3}"
bash scripts/env.sh runtime
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
if ls dist/artdef-*.zip >/dev/null 2>&1; then
  echo "demo: extension zips (Blender 4.5 LTS to 5.3: Edit > Preferences > Get Extensions > Install from Disk):"
  ls -l dist/artdef-*.zip
else
  echo "demo: to install into Blender 4.5 LTS to 5.3, build the zips: make extension (dist/artdef-*-<platform>.zip)"
fi
