#!/usr/bin/env bash
# Runs one libFuzzer target as a test: replays the committed corpus, then fuzzes for SECONDS.
# New inputs go to a scratch folder (removed afterwards); a crash, leak, timeout or
# out-of-memory input is kept in the scratch folder, printed, and fails the test.
# Usage: run_fuzzer.sh BINARY CORPUS_DIR SECONDS MAX_LEN
set -uo pipefail
bin=$1 corpus=$2 seconds=$3 max_len=$4
work=$(mktemp -d "${TMPDIR:-/tmp}/slst-fuzz-$(basename "$bin").XXXXXX")
mkdir -p "$work/new"
cd "$work"
"$bin" -max_total_time="$seconds" -max_len="$max_len" -timeout=20 -rss_limit_mb=3072 \
    -print_final_stats=1 -artifact_prefix="$work/" "$work/new" "$corpus"
rc=$?
if [ $rc -ne 0 ]; then
    echo "fuzz finding kept in $work:" >&2
    ls -la "$work" >&2
    for f in "$work"/crash-* "$work"/leak-* "$work"/timeout-* "$work"/oom-*; do
        [ -f "$f" ] && { echo "== $f (base64)"; base64 -w0 "$f" | head -c 4000; echo; } >&2
    done
    exit $rc
fi
rm -rf "$work"
