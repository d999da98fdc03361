#!/usr/bin/env bash
# The station's main job on built-in defaults, no hardware and no data files:
#   stage-sim (a Modbus TCP stage server on loopback) + the real Modbus stage driver,
#   the simulated camera over a virtual slide of eight generated sections (two damaged),
#   the built-in atlas, and the demo plan (docs/examples/). slicestationd scans the plan,
#   registers every section as it is captured, flags the damaged ones and raises alerts;
#   this script then prints what a technician would look at and stops the daemon cleanly.
# Everything lands in the output directory (default slicestation-demo/).
set -euo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
out=$(realpath -m "${1:-slicestation-demo}")
bash "$here/scripts/build.sh"
bin="$here/build"
slicectl="$bin/daemon/slicectl"

rm -rf "$out"
mkdir -p "$out"
pids=()
cleanup() {
    for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done
    wait 2>/dev/null || true
}
trap cleanup EXIT

"$bin/simulators/stage-sim" --preset oriental-az --port 0 --slaves 1 2 3 >"$out/stage-sim.log" 2>&1 &
pids+=($!)
port=""
for _ in $(seq 100); do
    port=$(sed -n 's/^stage-sim: tcp 127\.0\.0\.1:\([0-9]*\)$/\1/p' "$out/stage-sim.log")
    [ -n "$port" ] && break
    sleep 0.1
done
[ -n "$port" ] || { echo "demo: stage-sim did not start:" >&2; cat "$out/stage-sim.log" >&2; exit 1; }
echo "demo: stage-sim serves Modbus TCP on 127.0.0.1:$port"

sed -e "s/^port = 5020 .*/port = $port/" "$here/docs/examples/demo-station.toml" >"$out/station.toml"
"$bin/daemon/slicestationd" --config "$out/station.toml" --state-dir "$out/state" --http-port 0 \
    --plan "$here/docs/examples/demo-plan.toml" 2>"$out/slicestationd.log" &
daemon=$!
pids+=($daemon)
for _ in $(seq 300); do
    [ -s "$out/state/http.port" ] && break
    kill -0 "$daemon" 2>/dev/null || { cat "$out/slicestationd.log" >&2; exit 1; }
    sleep 0.1
done
url="http://127.0.0.1:$(cat "$out/state/http.port")"
echo "demo: slicestationd is up, HTTP API on $url (log: $out/slicestationd.log)"
echo "demo: open $url/ in a browser on this machine to watch the run"

# Follow the run until it ends (bounded).
state=""
for _ in $(seq 600); do
    state=$("$slicectl" runs --json --url "$url" | sed -n 's/^    "state": "\(.*\)",\{0,1\}$/\1/p' | head -1)
    case "$state" in finished|paused|failed|cancelled) break ;; esac
    kill -0 "$daemon" 2>/dev/null || { cat "$out/slicestationd.log" >&2; exit 1; }
    sleep 1
done
echo "demo: run 1 is $state"
echo
echo "== alerts (open) =="
"$slicectl" alerts --url "$url"
echo
echo "== run 1, per section (also in $out/run-1.csv) =="
"$slicectl" export 1 --format csv --url "$url" --output "$out/run-1.csv"
cut -d, -f2,3,5,8,9,10,13,15,17,19 "$out/run-1.csv" | column -s, -t 2>/dev/null || cat "$out/run-1.csv"
echo
if [ "${SLST_DEMO_KEEP:-0}" = 1 ]; then
    echo "demo: SLST_DEMO_KEEP=1: the daemon stays up ($url/); Ctrl-C stops it"
    wait "$daemon" || true
fi
kill -TERM "$daemon"
wait "$daemon" || true
grep -E "SIMULATED|ALERT|stopp" "$out/slicestationd.log" | sed 's/^<[0-9]>/  /'
echo
echo "demo: images and overlays are under $out/state/runs/1/; the journal is $out/state/journal.sqlite"
[ "$state" = finished ]
