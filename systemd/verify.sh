#!/usr/bin/env bash
# Verify systemd/edod.service with `systemd-analyze verify` against the built edod
# (verify checks that ExecStart exists, so the unit is checked with the path replaced).
# Usage: systemd/verify.sh [path/to/edod]   (default target/debug/edod)
set -euo pipefail
cd "$(dirname "$0")/.."
edod="$(realpath "${1:-target/debug/edod}")"
if ! command -v systemd-analyze >/dev/null 2>&1; then
  echo "systemd-analyze not available: unit not verified" >&2
  exit 0
fi
tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT
sed "s#/usr/bin/edod#$edod#g" systemd/edod.service > "$tmp/edod.service"
out="$(SYSTEMD_LOG_LEVEL=notice systemd-analyze verify "$tmp/edod.service" 2>&1 || true)"
# Messages about other units of the host are not ours.
mine="$(printf '%s\n' "$out" | grep -F 'edod.service' || true)"
if [ -n "$mine" ]; then
  printf '%s\n' "$mine" >&2
  exit 1
fi
echo "systemd/edod.service verified"
