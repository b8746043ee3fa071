#!/usr/bin/env bash
# Build the edo Debian package (edod, edoctl, hil-sim, the unit, /etc/edo/edod.toml, the
# docs; metadata in Cargo.toml [package.metadata.deb]) and print the .deb's path.
# Usage: systemd/build-deb.sh [PROFILE [--no-build]]   (default release)
# CI packs `dev --no-build`: the binaries its `cargo test --workspace` built (a
# `cargo build` of the bins alone resolves features without the dev-dependencies and
# compiles much of the tree again), which cargo-deb 3.8 takes with a warning. Those
# binaries have edo's `sim` feature on (the test build unifies it), unused by them.
# hil-sim is a package of its own, built after edo's binaries and apart from them: built
# together, cargo would unify its `edo/sim` feature (the firmware models and test kits)
# into edod and edoctl, which must leave them out. Then `cargo deb --no-build` packs them.
set -euo pipefail
cd "$(dirname "$0")/.."
profile="${1:-release}"
build="${2:-}"
if ! cargo deb --version >/dev/null 2>&1; then
  echo "installing cargo-deb" >&2
  cargo install cargo-deb --version 3.8.0 --locked >&2
fi
if [ "$build" = "--no-build" ]; then
  dir="target/$([ "$profile" = dev ] && echo debug || echo "$profile")"
  for bin in edod edoctl hil-sim; do
    [ -x "$dir/$bin" ] || { echo "build-deb.sh --no-build: $dir/$bin is not built" >&2; exit 1; }
  done
else
  cargo build --locked --profile "$profile" -p edo --bins >&2
  cargo build --locked --profile "$profile" -p hil-sim --bins >&2
fi
# --strip: the release profile keeps line tables for backtraces (debug = 1); a host
# needs the binaries only (about 60 MB each with them, a few MB without).
out="$(cargo deb -p edo --no-build --locked --profile "$profile" --strip)"
deb="$(printf '%s\n' "$out" | grep '\.deb$' | tail -n 1)"
if [ ! -f "$deb" ]; then
  printf 'cargo deb made no package:\n%s\n' "$out" >&2
  exit 1
fi
echo "$deb"
