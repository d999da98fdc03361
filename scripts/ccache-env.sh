# Sourced by the build scripts: compile through ccache when it is installed (install-deps.sh
# installs it). Paths inside the checkout are hashed relative to it, so a fresh clone in another
# folder (CI's) reuses what an earlier build of the same sources compiled; a cold cache only
# costs the ordinary compile.
slst_launcher=()
if command -v ccache >/dev/null; then
    export CCACHE_BASEDIR="$here"
    export CCACHE_NOHASHDIR=1
    slst_launcher=(-DCMAKE_CXX_COMPILER_LAUNCHER=ccache -DCMAKE_C_COMPILER_LAUNCHER=ccache)
fi
