#!/usr/bin/env bash
# Install the edo Debian package on this machine (as root, with or without a running
# systemd, e.g. in a container) and check it as a printer host would use it: the
# configuration checks, the CLIs run, the edo user and group exist, installing again
# changes nothing, and edod runs as the edo user on the installed configuration (the
# simulated machine) and answers an operator in the edo group on /run/edo/edod.sock.
# Purges the package at the end.
# Usage: systemd/check-deb.sh PATH/TO/edo_*.deb
set -euo pipefail
deb="$1"
if [ "$(id -u)" != 0 ]; then
  echo "check-deb.sh installs a package: run it as root" >&2
  exit 1
fi

edod_pid=""
cleanup() {
  if [ -n "$edod_pid" ]; then kill -TERM "$edod_pid" 2>/dev/null || true; fi
  dpkg --purge edo >/dev/null 2>&1 || true
}
trap cleanup EXIT

dpkg -i "$deb"
edod --check-config /etc/edo/edod.toml
edod --version
edoctl --version
hil-sim --version
getent passwd edo
getent group edo
id -nG edo | tr ' ' '\n' | grep -qx dialout || { echo "edo is not in dialout" >&2; exit 1; }
dpkg-query -W -f='${Conffiles}\n' edo | grep -q ' /etc/edo/edod.toml ' ||
  { echo "/etc/edo/edod.toml is not a conffile" >&2; exit 1; }
test -f /usr/share/doc/edo/api.md   # the unit's Documentation=
unit="$(dpkg -L edo | grep '/systemd/system/edod.service$')"
grep -q '^ExecStart=/usr/bin/edod ' "$unit"

# Again (an upgrade to the same version): the maintainer scripts are idempotent.
uid="$(id -u edo)"
dpkg -i "$deb"
[ "$(id -u edo)" = "$uid" ]

# edod as the unit runs it (user edo, the directories systemd would create), for a few
# seconds: it starts hil-sim from /usr/bin and answers on its socket.
install -d -o edo -g edo -m 0750 /run/edo /var/lib/edo
setpriv --reuid=edo --regid=edo --init-groups -- \
  timeout 60 /usr/bin/edod --config /etc/edo/edod.toml &
edod_pid=$!
ok=""
for _ in $(seq 1 100); do
  if [ -S /run/edo/edod.sock ] && timeout 10 edoctl status >/dev/null 2>&1; then
    ok=yes
    break
  fi
  sleep 0.2
done
# An operator: any user in the edo group may use the socket.
operator_ok=""
if setpriv --reuid=nobody --regid=nogroup --groups="$(getent group edo | cut -d: -f3)" -- \
  timeout 10 edoctl status; then
  operator_ok=yes
fi
# Anyone else may not.
if setpriv --reuid=nobody --regid=nogroup --clear-groups -- timeout 10 edoctl status 2>/dev/null; then
  operator_ok=""
fi
kill -TERM "$edod_pid" 2>/dev/null || true
wait "$edod_pid" || true
edod_pid=""
if [ -z "$ok" ]; then
  echo "the installed edod did not answer on /run/edo/edod.sock" >&2
  exit 1
fi
if [ -z "$operator_ok" ]; then
  echo "/run/edo/edod.sock: members of the edo group (only) should reach edod" >&2
  exit 1
fi

dpkg --purge edo
trap - EXIT
echo "Debian package $deb: installed, checked, purged"
