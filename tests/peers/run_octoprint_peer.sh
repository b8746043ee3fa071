#!/usr/bin/env bash
# The OctoPrint peer check for .ci/run: OctoPrint's virtual printer (PyPI `octoprint`,
# pinned below) in a venv, then tests/octoprint_peer.rs against it. Needs python3 with
# venv + pip and network to PyPI; fails when either is missing. With --install it only
# installs the venv and prints its python (.ci/run exports it as EDO_OCTOPRINT_PY).
#
# Pinned to 1.11.8: the resend handling of its virtual printer is the same code from
# 1.9.3 to 1.11.8 (compared), with two faults of its own, both in every one of them:
# after a line-number error its checksum-error path names a line too far (it counts
# rejected lines in `current_line`), which a pty never reaches (nothing corrupts bytes);
# and its `resend_ratio` takes the line and asks for the next one (the line is lost
# whatever the host does), which tests/peers/octoprint_shim.py corrects. So the newest.
set -euo pipefail
cd "$(dirname "$0")/../.."
OCTOPRINT_VERSION=1.11.8
PY=${PYTHON:-python3.11}
command -v "$PY" >/dev/null 2>&1 || PY=python3
VENV=target/octoprint-venv
if [ ! -x "$VENV/bin/python" ]; then
  if ! "$PY" -m venv "$VENV" || ! "$VENV/bin/pip" install -q "octoprint==$OCTOPRINT_VERSION" >&2; then
    echo "could not install octoprint $OCTOPRINT_VERSION from PyPI" >&2
    rm -rf "$VENV"; exit 1
  fi
fi
if [ "${1:-}" = "--install" ]; then
  echo "$PWD/$VENV/bin/python"; exit 0
fi
# Through LineHost (octoprint_peer) and through edod (daemon_gcode's octoprint test).
EDO_OCTOPRINT_PY="$VENV/bin/python" cargo test --locked --test octoprint_peer --test daemon_gcode \
  octoprint -- --nocapture
