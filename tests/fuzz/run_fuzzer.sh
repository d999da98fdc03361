#!/usr/bin/env bash
# Runs one libFuzzer target as a test: replays the committed corpus, then fuzzes for SECONDS.
# New inputs go to a scratch folder (removed afterwards); a crash, leak, timeout or
# out-of-memory input is kept in the scratch folder, printed, and fails the test.
# The fuzzer's own output (thousands of decoder warnings) goes to fuzz.log in that folder; the
# test prints its final statistics, or on a finding the log's last 80 lines and the input, so
# that a CI log cut in the middle still shows what was found.
# Usage: run_fuzzer.sh BINARY CORPUS_DIR SECONDS MAX_LEN
set -uo pipefail
bin=$1 corpus=$2 seconds=$3 max_len=$4
work=$(mktemp -d "${TMPDIR:-/tmp}/slst-fuzz-$(basename "$bin").XXXXXX")
mkdir -p "$work/new"
cd "$work"
"$bin" -max_total_time="$seconds" -max_len="$max_len" -timeout=20 -rss_limit_mb=3072 \
    -print_final_stats=1 -artifact_prefix="$work/" "$work/new" "$corpus" >"$work/fuzz.log" 2>&1
rc=$?
if [ $rc -ne 0 ]; then
    echo "fuzz finding (exit $rc) kept in $work; the fuzzer's last 80 lines:"
    tail -n 80 "$work/fuzz.log"
    ls -la "$work"
    for f in "$work"/crash-* "$work"/leak-* "$work"/timeout-* "$work"/oom-*; do
        [ -f "$f" ] && { echo "== $f (base64)"; base64 -w0 "$f" | head -c 4000; echo; }
    done
    exit $rc
fi
grep -a -E "^(#[0-9]+[[:space:]]+DONE|Done |stat::)" "$work/fuzz.log"
rm -rf "$work"
