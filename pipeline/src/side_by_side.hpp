#pragma once
/// Independent pieces of one pipeline call, side by side on OpenCV's threads (private to the
/// pipeline's sources). The pipeline owns no thread (docs/architecture.md, "Threads in the
/// pipeline"); cv::setNumThreads is the one setting, and with one thread, or when called inside
/// another parallel region, the pieces run in turn on the caller.

#include <opencv2/core/utility.hpp>

namespace slicestation::pipeline {

/// Runs `task(i)` for i in [0, n). The tasks must be independent, each writing only its own
/// results, so that what comes out does not depend on the threads.
template <class Task> void runTasks(int n, const Task& task) {
    if (n <= 0)
        return;
    cv::parallel_for_(
        cv::Range(0, n),
        [&](const cv::Range& r) {
            for (int i = r.start; i < r.end; ++i)
                task(i);
        },
        n);
}

} // namespace slicestation::pipeline
