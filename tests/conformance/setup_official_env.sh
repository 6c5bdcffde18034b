#!/usr/bin/env bash
# Builds the official WOSAC package's own environment (TensorFlow; never the project's) and reruns the conformance
# record. Usage: bash tests/conformance/setup_official_env.sh [VENV]   (default .venv-waymo)
# The package is pinned as the issue measured it; on Python 3.11 pip resolves tensorflow 2.13.0,
# tensorflow-probability 0.21.0, numpy 1.23.5 (about 2 GB, a few minutes).
set -euo pipefail
VENV=${1:-.venv-waymo}
PY=${PYTHON:-python3.11}
HERE=$(cd "$(dirname "$0")" && pwd)
if [ ! -x "$VENV/bin/python" ]; then
  "$PY" -m venv "$VENV"
  "$VENV/bin/pip" install --quiet "waymo-open-dataset-tf-2-12-0==1.6.7"
fi
"$VENV/bin/python" -c "import waymo_open_dataset.wdl_limited.sim_agents_metrics.metrics" 2>/dev/null \
  || { echo "setup_official_env.sh: $VENV has no working waymo_open_dataset" >&2; exit 2; }
# the scenes are written by the project (its environment), the record by the official code (its own)
python "$HERE/make_scenes.py"
"$VENV/bin/python" "$HERE/run_official.py" --scenes "$HERE/scenes.npz" --out "$HERE/official.json"
