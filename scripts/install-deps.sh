#!/usr/bin/env bash
# Installs every Debian 12 package slicestation needs to build, test and run.
# The one list of build and test dependencies; scripts/demo.sh and scripts/test.sh call it.
set -euo pipefail
packages=(
    build-essential cmake ninja-build pkg-config ccache
    libopencv-dev libeigen3-dev libcgal-dev libgmp-dev libmpfr-dev
    libtiff-dev zlib1g-dev libpng-dev libturbojpeg0-dev libpugixml-dev
    nlohmann-json3-dev libcli11-dev libtomlplusplus-dev libcpp-httplib-dev libssl-dev
    libmodbus-dev libcamera-dev libsqlite3-dev libsystemd-dev
    libgtest-dev libgmock-dev
    systemd  # systemd-analyze, for the unit file checks (tests/systemd)
    chromium chromium-driver  # headless browser tests of the web page (tests/web)
    clang-format  # scripts/check-format.sh: the tree follows .clang-format
    python3  # scripts/check-daemon-size.py: the daemon's file and function sizes
    clang-14 libclang-rt-14-dev  # the checking build: ASan + UBSan and libFuzzer (scripts/build-checking.sh)
)
missing=()
for p in "${packages[@]}"; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if ((${#missing[@]})); then
    SUDO=""
    [ "$(id -u)" -eq 0 ] || SUDO="sudo"
    export DEBIAN_FRONTEND=noninteractive
    $SUDO apt-get update -qq
    $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}"
fi
