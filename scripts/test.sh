#!/usr/bin/env bash
# The test command: set up the environment (idempotent), build the extension,
# install the Khronos glTF validator locally, run the whole test suite.
# Extra arguments go to pytest.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
bash scripts/env.sh
bash scripts/install_validator.sh
exec "$ROOT/.venv/bin/python" -m pytest tests -q "$@"
