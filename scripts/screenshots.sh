#!/usr/bin/env bash
# Regenerate the viewer screenshots the docs show (docs/images/viewer_*.png): the browser test
# opens each app's default recording in rerun's web viewer in headless Chromium and copies its
# screenshots there. Needs what scripts/bootstrap.sh installs (Debian's chromium, playwright).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/bootstrap.sh
GRAPHOPT_SCREENSHOTS=docs/images exec .venv/bin/python -P -m pytest -q -m browser \
    tests/test_recording_browser.py "$@"
