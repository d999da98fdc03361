#!/usr/bin/env bash
# Checks a unit file with systemd-analyze, as CI does:
#   check_unit.sh UNIT MAX_EXPOSURE [EXTRA_LINE]
# 1. `systemd-analyze verify` on a copy whose ExecStart= binary is replaced by /bin/true (the
#    daemon is not installed where tests run; verify fails on a missing executable). Any
#    diagnostic counts as a failure, not just a non-zero exit: verify exits 0 on "Unknown key".
# 2. `systemd-analyze security --offline=yes`: fails above MAX_EXPOSURE (0 = best, 10 = worst).
# EXTRA_LINE, when given, is appended to [Service] (used to prove the check catches errors).
set -euo pipefail
unit=$1
max=$2
extra=${3:-}
command -v systemd-analyze >/dev/null || {
    echo "systemd-analyze not found: scripts/install-deps.sh installs the systemd package" >&2
    exit 1
}
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
copy="$work/$(basename "$unit")"
sed -E 's|^ExecStart=[^ ]+|ExecStart=/bin/true|' "$unit" > "$copy"
if [ -n "$extra" ]; then
    sed -i "/^\[Service\]/a $extra" "$copy"
fi

status=0
if ! out=$(systemd-analyze verify "$copy" 2>&1) || [ -n "$out" ]; then
    echo "systemd-analyze verify failed:" >&2
    echo "$out" >&2
    status=1
else
    echo "verify: OK"
fi

security=$(systemd-analyze security --offline=yes "$copy" 2>&1) || true
score=$(sed -n 's/.*Overall exposure level for [^:]*: \([0-9.]*\).*/\1/p' <<<"$security")
if [ -z "$score" ]; then
    echo "systemd-analyze security gave no score:" >&2
    echo "$security" >&2
    exit 1
fi
echo "security: exposure $score (limit $max)"
if ! awk -v s="$score" -v m="$max" 'BEGIN { exit !(s <= m) }'; then
    echo "exposure $score is above $max:" >&2
    grep '✗' <<<"$security" >&2 || true
    status=1
fi
exit $status
