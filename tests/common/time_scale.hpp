#pragma once
// SLST_TEST_TIME_SCALE: how much slower than the release build a test may run. The sanitizer
// build sets it (scripts/test.sh); every deadline and time bound of a test that measures the
// daemon's answers is stretched by it, and the release build keeps its own bounds (1).
#include <cstdlib>

namespace slicestation::testing_time {

/// The factor from SLST_TEST_TIME_SCALE, in [1, 100]; 1 when unset or out of range.
inline double timeScale() {
    const char* v = std::getenv("SLST_TEST_TIME_SCALE");
    const double f = v ? std::atof(v) : 1.0;
    return f >= 1.0 && f <= 100.0 ? f : 1.0;
}

} // namespace slicestation::testing_time
