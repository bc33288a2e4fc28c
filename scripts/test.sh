#!/usr/bin/env bash
# Set up (if needed) and run the test suite; extra arguments go to pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/bootstrap.sh
echo "test: .venv/bin/python -P -m pytest -q${*:+ $*}"
exec .venv/bin/python -P -m pytest -q "$@"
