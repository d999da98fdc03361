#!/usr/bin/env bash
# The station's main job on built-in defaults: no hardware, no data files. Until the daemon
# exists this generates a section from the built-in atlas, registers it, prints the result and
# writes an overlay (slicestation-demo/overlay.png).
set -euo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
bash "$here/scripts/build.sh"
"$here/build/daemon/slicectl" demo --output-dir "${1:-slicestation-demo}"
