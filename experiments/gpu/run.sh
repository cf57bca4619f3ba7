#!/usr/bin/env bash
# GPU readiness in one run (about 5 minutes on an accelerator): tracer photons/ms, the 256 x 256 x 21
# render, one fit re-trace; rows go to experiments/BENCHMARKS.md. `run.sh --small` runs CPU smoke
# sizes (CI). Uses the project's .venv when there is one (make test creates it).
set -euo pipefail
cd "$(dirname "$0")/../.."
PY=python3
[ -x .venv/bin/python ] && PY=.venv/bin/python
exec "$PY" experiments/gpu/run.py "$@"
