#!/usr/bin/env bash
# Installs the dependencies (Debian 12 packages) and builds everything into ./build.
set -euo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
bash "$here/scripts/install-deps.sh"
source "$here/scripts/ccache-env.sh"
cmake -S "$here" -B "$here/build" -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo -DSLST_WERROR=ON \
    "${slst_launcher[@]}" >/dev/null
cmake --build "$here/build" -j "$(nproc)"
