#!/usr/bin/env bash
# Installs what is needed, builds, and runs every test (all labels), then the sanitizers' share again:
#   build/        the release build (gcc), every test;
#   build-check/  the checking build (clang, AddressSanitizer + UndefinedBehaviorSanitizer +
#                 LeakSanitizer on everything), every test again but the accuracy figures (label
#                 accuracy: seven of them, one per path, run there too) and the benchmarks' smoke
#                 tests, and each fuzz target (label fuzz) replaying its committed corpus and
#                 fuzzing for SLST_FUZZ_SECONDS (30).
# Before the tests, scripts/check-format.sh checks that every C++ file follows .clang-format and
# scripts/check-daemon-size.py that no daemon/ file exceeds 600 lines nor any function 100.
# CI runs exactly this. SLST_TEST_CHECKING=0 skips the checking build (a quicker local run).
set -euo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
bash "$here/scripts/build.sh"
bash "$here/scripts/check-format.sh"
python3 "$here/scripts/check-daemon-size.py" --top 3
if [ ! -d "$here/../shared" ]; then
    echo "note: ../shared is absent; tests that need the real atlas and sections will skip" >&2
fi
(cd "$here/build" && ctest --output-on-failure -j "$(nproc)" --timeout 900)
if [ "${SLST_TEST_CHECKING:-1}" = "0" ]; then
    echo "note: SLST_TEST_CHECKING=0: the sanitizer build and the fuzz targets did not run" >&2
    exit 0
fi
bash "$here/scripts/build-checking.sh"
export ASAN_OPTIONS="detect_leaks=1:strict_string_checks=1:check_initialization_order=1:detect_stack_use_after_return=1"
export LSAN_OPTIONS="suppressions=$here/tests/sanitizer/lsan.supp:print_suppressions=0"
export UBSAN_OPTIONS="print_stacktrace=1:halt_on_error=1:suppressions=$here/tests/sanitizer/ubsan.supp"
# The daemon runs several times slower under the sanitizers: the process tests' deadlines stretch.
export SLST_TEST_TIME_SCALE=4
cd "$here/build-check"
ctest --output-on-failure -j "$(nproc)" --timeout 1800 -LE accuracy
# The accuracy tests check figures, which the release build has checked; under the sanitizers
# one per path runs: real atlas planes clean and damaged, the region warp, the template-like
# intensity warp, the damage kinds, the real torn sections, and the plane finder (docs/testing.md).
sentinels=(
    'RegistrationAccuracy\.RealAtlasPlanesCleanAndDamaged'
    'RegistrationAccuracy\.TheRegionWarpFollowsAnyStainBeyondTheGeometricStages'
    'RegistrationAccuracy\.TheIntensityWarpFollowsTemplateLikeSectionsBeyondTheAffine'
    'DamageGroundTruth\.EachKindIsFlaggedLocatedAndKeptOutOfTheFit'
    'DamageRealSeries\.TornSectionsAreFlaggedAndCleanOnesAreNot'
    'AtlasMatching\.FindsThePlaneOfGeneratedSections'
    'AtlasMatching\.BadInputsAreErrors')
pattern="^($(IFS='|'; echo "${sentinels[*]}"))\$"
# A renamed test would drop out of the list silently: each name must match one test.
found=$(ctest -N -L accuracy -R "$pattern" | sed -n 's/^Total Tests: //p')
if [ "$found" != "${#sentinels[@]}" ]; then
    echo "scripts/test.sh: ${found:-0} of the ${#sentinels[@]} accuracy tests named for the checking build exist" >&2
    exit 1
fi
ctest --output-on-failure -j "$(nproc)" --timeout 1800 -L accuracy -R "$pattern"
