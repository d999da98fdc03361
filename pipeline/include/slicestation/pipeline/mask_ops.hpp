#pragma once
/// Small operations on binary masks (CV_8U, non-zero = set) shared by the pipeline's steps.

#include <opencv2/core.hpp>

#include <vector>

namespace slicestation::pipeline {

/// The mask with every hole filled (outer contours drawn solid).
cv::Mat fillHoles(const cv::Mat& mask);

/// Every pixel of every outer contour, as points.
std::vector<cv::Point2f> outerContourPoints(const cv::Mat& mask);

/// The k-th smallest of `values` (k < size), the value std::nth_element puts at k (the order of
/// `values` changes); a histogram of the values' top bits first, so large sets cost two passes.
/// A -0 and a +0 compare equal and either may be returned.
float kthSmallest(std::vector<float>& values, size_t k);

/// The q-quantile (0..1) of the values of `f32` (CV_32F) where `valid` (CV_8U, same size) is
/// set, on a strided sample of about 250,000 pixels; 0 when none is set.
float percentile(const cv::Mat& f32, double q, const cv::Mat& valid);

/// cv::connectedComponentsWithStats (8-connected, CV_32S labels) run on the box holding the
/// mask's set pixels only, which is what the labelling's time goes with: the same labels on the
/// mask's whole size (0 outside the box) and the same stats rows (boxes in the mask's
/// coordinates) as on the whole mask. The box starts on even coordinates, so that the labelling's
/// 2 x 2 blocks lie as on the whole mask and the components are numbered alike. Row 0 (the
/// background) carries its area; its box is the whole mask. Returns the number of labels.
int labelComponents(const cv::Mat& mask, cv::Mat& labels, cv::Mat& stats);

} // namespace slicestation::pipeline
