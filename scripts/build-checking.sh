#!/usr/bin/env bash
# The checking build in ./build-check: clang with AddressSanitizer and UndefinedBehaviorSanitizer
# on every target, and the libFuzzer targets of tests/fuzz. Dependencies as for build.sh.
set -euo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
bash "$here/scripts/install-deps.sh"
source "$here/scripts/ccache-env.sh"
cmake -S "$here" -B "$here/build-check" -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo \
    -DCMAKE_CXX_COMPILER=clang++-14 -DSLST_SANITIZE=address,undefined -DSLST_FUZZ=ON -DSLST_BUILD_BENCHMARKS=OFF \
    -DSLST_FUZZ_SECONDS="${SLST_FUZZ_SECONDS:-30}" "${slst_launcher[@]}" >/dev/null
cmake --build "$here/build-check" -j "$(nproc)"
