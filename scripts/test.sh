#!/usr/bin/env bash
# The test command: set up the environment (idempotent), build the extension,
# install the Khronos glTF validator locally, run the whole test suite.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
bash scripts/env.sh

# Khronos glTF validator (npm package of KhronosGroup/glTF-Validator) into .tools/.
VALIDATOR_VERSION=2.0.0-dev.3.10
if [ -f .tools/node_modules/gltf-validator/package.json ] &&
   grep -q "\"version\": \"$VALIDATOR_VERSION\"" .tools/node_modules/gltf-validator/package.json; then
  echo "test: gltf-validator $VALIDATOR_VERSION already in .tools/"
elif command -v npm >/dev/null 2>&1 && command -v node >/dev/null 2>&1; then
  echo "test: installing gltf-validator $VALIDATOR_VERSION into .tools/"
  npm install --prefix "$ROOT/.tools" --no-audit --no-fund --loglevel=error \
    "gltf-validator@$VALIDATOR_VERSION"
else
  echo "test: node/npm not found: the glTF validation tests will be SKIPPED (apt-get install nodejs npm)"
fi

exec "$ROOT/.venv/bin/python" -m pytest tests -q "$@"
