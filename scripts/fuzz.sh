#!/usr/bin/env bash
# Grows one fuzz target's committed corpus: fuzzes for SECONDS (default 600) on the checking
# build, then merges what it found into tests/fuzz/corpus/NAME (only inputs that add coverage).
# Usage: scripts/fuzz.sh NAME [SECONDS]      e.g. scripts/fuzz.sh fuzz_http 600
set -euo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
name=$1 seconds=${2:-600}
bin="$here/build-check/tests/fuzz/$name"
[ -x "$bin" ] || bash "$here/scripts/build-checking.sh"
corpus="$here/tests/fuzz/corpus/$name"
max_len=$(sed -n "s/^slst_add_fuzzer($name \([0-9]*\).*/\1/p" "$here/tests/fuzz/CMakeLists.txt")
work=$(mktemp -d "${TMPDIR:-/tmp}/slst-fuzz-$name.XXXXXX")
mkdir -p "$work/new"
export ASAN_OPTIONS="detect_leaks=1"
export LSAN_OPTIONS="suppressions=$here/tests/sanitizer/lsan.supp:print_suppressions=0"
export UBSAN_OPTIONS="print_stacktrace=1:halt_on_error=1:suppressions=$here/tests/sanitizer/ubsan.supp"
(cd "$work" && "$bin" -max_total_time="$seconds" -max_len="$max_len" -timeout=20 -rss_limit_mb=3072 \
    -print_final_stats=1 -artifact_prefix="$work/" "$work/new" "$corpus")
(cd "$work" && "$bin" -merge=1 -max_len="$max_len" -timeout=20 -rss_limit_mb=3072 "$corpus" "$work/new")
rm -rf "$work"
echo "$name: $(ls "$corpus" | wc -l) inputs in $corpus"
