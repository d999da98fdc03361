#pragma once
/// Small operations on binary masks (CV_8U, non-zero = set) shared by the pipeline's steps.

#include <opencv2/core.hpp>

#include <vector>

namespace slicestation::pipeline {

/// The mask with every hole filled (outer contours drawn solid).
cv::Mat fillHoles(const cv::Mat& mask);

/// Every pixel of every outer contour, as points.
std::vector<cv::Point2f> outerContourPoints(const cv::Mat& mask);

} // namespace slicestation::pipeline
