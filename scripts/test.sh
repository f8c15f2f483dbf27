#!/usr/bin/env bash
# Run the whole test suite (sets up first). Extra arguments go to pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
# the floors of docs/architecture.md: imports point down (contracts in pyproject.toml)
.venv/bin/lint-imports --no-cache
# one pytest worker per CPU (pytest-xdist), each test file on one worker (its module fixtures built once); the suite
# is mostly single-threaded Python, so its files run side by side on the cores; the files are handed out in the
# collection's order, which tests/conftest.py sorts longest first (--no-loadscope-reorder), so the workers finish
# together. `scripts/test.sh -n 0 ...` runs it serially (later options win).
exec .venv/bin/python -m pytest -q -n auto --dist loadfile --no-loadscope-reorder "$@"
