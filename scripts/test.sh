#!/usr/bin/env bash
# Run the whole test suite (sets up first). Extra arguments go to pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
# the floors of docs/architecture.md: imports point down (contracts in pyproject.toml)
.venv/bin/lint-imports --no-cache
exec .venv/bin/python -m pytest -q "$@"
