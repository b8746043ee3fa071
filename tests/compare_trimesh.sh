#!/usr/bin/env bash
# Independent check of section areas against trimesh (PyPI), for .ci/run after `cargo test`
# (which builds examples/slice_areas). Needs python3 with venv + pip and network to PyPI;
# skips with a note when either is missing or ../shared/meshes is absent.
set -euo pipefail
cd "$(dirname "$0")/.."
if [ ! -d ../shared/meshes ]; then
  echo "note: ../shared/meshes missing, trimesh comparison skipped"; exit 0
fi
PY=${PYTHON:-python3.11}
command -v "$PY" >/dev/null 2>&1 || PY=python3
VENV=target/trimesh-venv
if [ ! -x "$VENV/bin/python" ]; then
  if ! "$PY" -m venv "$VENV" || ! "$VENV/bin/pip" install -q trimesh shapely numpy scipy rtree networkx lxml; then
    echo "note: could not install trimesh from PyPI, comparison skipped"; rm -rf "$VENV"; exit 0
  fi
fi
EDO=target/debug/examples/slice_areas
[ -x "$EDO" ] || cargo build --locked --profile test --example slice_areas
"$VENV/bin/python" tests/compare_trimesh.py --edo "$EDO"
