#!/usr/bin/env bash
# Whole-process timing of the registration (issue 17, "Speed"): `slicectl register` as a process
# against elastix + transformix as processes, on the same generated 1500x1100 sections, each on
# one core (taskset -c 0) and each on both cores (slicectl's default threads, elastix -threads 2);
# then one 8000x5000 section through `slicectl register` under /usr/bin/time -v (wall time and
# peak memory). Prints the tables.
#
# Usage: scripts/bench-registration.sh [build-dir] [sections]   (default build/, 4 sections,
# each timed twice; sections alternate the first and the second generator family)
set -euo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
build=$(realpath -m "${1:-$here/build}")
sections=${2:-4}
slicectl="$build/daemon/slicectl"
make="$build/tests/benchmarks/slst_make_section"
for b in "$slicectl" "$make"; do
    [ -x "$b" ] || { echo "missing $b: build slicectl and slst_make_section first" >&2; exit 2; }
done
command -v elastix >/dev/null && command -v transformix >/dev/null ||
    { echo "elastix/transformix not installed" >&2; exit 2; }
work=$(mktemp -d /tmp/slst-bench-reg.XXXXXX)
trap 'rm -rf "$work"' EXIT

now() { date +%s.%N; }
ours=() theirs=() ours2=() theirs2=()
for ((i = 0; i < sections; i++)); do
    fam=$(( i % 2 == 0 ? 1 : 2 ))
    d="$work/s$i"
    "$make" --family "$fam" --seed $((300 + i)) --plane $(( (i * 11) % 48 )) --size 1500x1100 \
        --output-dir "$d" --elastix-dir "$d/elastix" >/dev/null
    for rep in 1 2; do
        t0=$(now)
        taskset -c 0 "$slicectl" register --atlas "$d/atlas.tif" --image "$d/section.tif" \
            --points "$d/points.csv" --output "$d/out.json" >/dev/null
        t1=$(now)
        ours+=("$(echo "$t1 - $t0" | bc -l)")
        cp "$d/out.json" "$work/cpu-$i-$rep.json"
        e="$d/elastix"
        t0=$(now)
        taskset -c 0 elastix -f "$e/fixed.mha" -m "$e/moving.mha" -p "$e/affine.txt" \
            -p "$e/bspline.txt" -out "$e" -threads 1 >"$e/elastix.out" 2>&1
        taskset -c 0 transformix -def "$e/points.txt" -tp "$e/TransformParameters.1.txt" \
            -out "$e" -threads 1 >"$e/transformix.out" 2>&1
        t1=$(now)
        theirs+=("$(echo "$t1 - $t0" | bc -l)")
        # Both cores: slicectl with its default threads (one per core), elastix with two.
        t0=$(now)
        "$slicectl" register --atlas "$d/atlas.tif" --image "$d/section.tif" \
            --points "$d/points.csv" --output "$d/out2.json" >/dev/null
        t1=$(now)
        ours2+=("$(echo "$t1 - $t0" | bc -l)")
        python3 - "$d/out.json" "$d/out2.json" <<'PY' ||
import json, sys
a, b = (json.load(open(f)) for f in sys.argv[1:])
fields = [open(f[:-len(".json")] + ".field.tif", "rb").read() for f in sys.argv[1:]]
for r in (a, b):
    for k in ("timings_ms", "cpu_timings_ms"):
        r.pop(k)
    r["mapping"].pop("field")
sys.exit(a != b or fields[0] != fields[1])
PY
            { echo "section $i: the two-core result differs from the one-core result" >&2; exit 1; }
        t0=$(now)
        elastix -f "$e/fixed.mha" -m "$e/moving.mha" -p "$e/affine.txt" \
            -p "$e/bspline.txt" -out "$e" -threads 2 >"$e/elastix.out" 2>&1
        transformix -def "$e/points.txt" -tp "$e/TransformParameters.1.txt" \
            -out "$e" -threads 2 >"$e/transformix.out" 2>&1
        t1=$(now)
        theirs2+=("$(echo "$t1 - $t0" | bc -l)")
    done
done
median() { printf '%s\n' "$@" | sort -g | awk '{v[NR]=$1} END {print (NR%2 ? v[(NR+1)/2] : (v[NR/2]+v[NR/2+1])/2)}'; }
# A table of slicectl's times (ours_t) against elastix's (theirs_t), titled $1.
row() { # row TOOL TIMES...
    local tool=$1
    shift
    printf '%-28s %10.3f %10.3f %10.3f\n' "$tool" "$(median "$@")" \
        "$(printf '%s\n' "$@" | sort -g | head -1)" "$(printf '%s\n' "$@" | sort -g | tail -1)"
}
table() {
    printf '\n%s\n' "$1"
    printf '%-28s %10s %10s %10s\n' "tool" "median s" "min s" "max s"
    row "slicectl register" "${ours_t[@]}"
    row "elastix + transformix" "${theirs_t[@]}"
    printf 'elastix / slicectl: %.1fx\n' \
        "$(echo "$(median "${theirs_t[@]}") / $(median "${ours_t[@]}")" | bc -l)"
}
ours_t=("${ours[@]}") theirs_t=("${theirs[@]}")
table "$(printf 'whole processes on one core (taskset -c 0), %d sections of 1500x1100 px, twice each' "$sections")"
ours_t=("${ours2[@]}") theirs_t=("${theirs2[@]}")
table "whole processes on both cores (slicectl one thread per core, elastix -threads 2)"
# Process CPU time per step (result.json's cpu_timings_ms; "process" includes the process's
# start): what a step costs even when other work shares the machine.
printf '\nslicectl register, process CPU ms per step (median over the runs above; load %s)\n' \
    "$(cut -d' ' -f1-3 /proc/loadavg)"
python3 - "$work"/cpu-*.json <<'PY'
import json, statistics, sys
runs = [json.load(open(f))["cpu_timings_ms"] for f in sys.argv[1:]]
for step in runs[0]:
    print(f"{step:<16} {statistics.median(r[step] for r in runs):8.1f}")
PY

d="$work/big"
"$make" --family 1 --seed 77 --plane 20 --size 8000x5000 --output-dir "$d" >/dev/null
/usr/bin/time -v "$slicectl" register --atlas "$d/atlas.tif" --image "$d/section.tif" \
    --points "$d/points.csv" --output "$d/out.json" >/dev/null 2>"$d/time.txt"
wall=$(grep 'Elapsed (wall clock)' "$d/time.txt" | awk '{print $NF}')
rss=$(grep 'Maximum resident set size' "$d/time.txt" | awk '{print $NF}')
/usr/bin/time -v taskset -c 0 "$slicectl" register --atlas "$d/atlas.tif" --image "$d/section.tif" \
    --points "$d/points.csv" --output "$d/out.json" >/dev/null 2>"$d/time1.txt"
wall1=$(grep 'Elapsed (wall clock)' "$d/time1.txt" | awk '{print $NF}')
printf '\n8000x5000 section, slicectl register as a process: wall %s (2 cores), %s (taskset -c 0); peak RSS %.0f MB\n' \
    "$wall" "$wall1" "$(echo "$rss / 1024" | bc -l)"
