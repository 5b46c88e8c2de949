#!/usr/bin/env bash
# systemd-analyze verify on the shipped unit (ExecStart pointed at the built daemon, which
# verify requires to exist) and its offline security exposure, which must stay <= 2.5.
# Usage: verify_unit.sh UNIT PULSETRACKD
set -euo pipefail
unit=$1 daemon=$2
command -v systemd-analyze >/dev/null || { echo "SKIP: systemd-analyze not installed"; exit 77; }
dir=$(mktemp -d)
trap 'rm -rf "$dir"' EXIT
sed "s|/usr/sbin/pulsetrackd|$daemon|g" "$unit" >"$dir/pulsetrackd.service"
systemd-analyze verify "$dir/pulsetrackd.service"
score=$(systemd-analyze security --offline=yes "$dir/pulsetrackd.service" 2>&1 |
  sed -n 's/.*Overall exposure level for pulsetrackd.service: \([0-9.]*\).*/\1/p')
echo "systemd-analyze security: exposure $score"
[[ -n "$score" ]] || { echo "no security score"; exit 1; }
awk -v s="$score" 'BEGIN { exit !(s <= 2.5) }' || { echo "exposure $score > 2.5"; exit 1; }
