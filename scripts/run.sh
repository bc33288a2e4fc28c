#!/usr/bin/env bash
# Set up (if needed) and run the main job: bundle adjustment on the generated synthetic scene,
# with a rerun recording and before/after point clouds in ./out/. Extra arguments go to graphopt-bal.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/bootstrap.sh
mkdir -p out
echo "run: graphopt-bal${*:+ $*} -> out/bal.rrd, out/before.ply, out/after.ply, out/bal.json"
exec .venv/bin/graphopt-bal --rrd out/bal.rrd --ply-before out/before.ply --ply-after out/after.ply \
    --json out/bal.json "$@"
